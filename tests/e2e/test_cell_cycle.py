"""The whole cell as a user runs it: the server and the device simulators as
separate processes on loopback, driven over HTTP and watched over /ws.

The robot simulator answers JSON-RPC on its own port and the glue simulator
Modbus RTU on another; the server reaches them through its production clients
exactly as it would reach real hardware (ROBOT_IP, GLUE_CONTROLLER_PORT).
"""

from __future__ import annotations

import asyncio
import json
import re
from collections.abc import AsyncIterator
from pathlib import Path

import httpx
import pytest
import websockets

from server.drivers.glue_modbus import ModbusGlueDispenser
from server.drivers.robot_jsonrpc import JsonRpcRobot
from server.settings.model import Settings
from tests.conftest import is_waypoint
from tests.processes import server_process, simulator
from tests.serving import admin_headers, free_port

# One cell serves the module's tests in order (the log test reads what the e-stop test
# left): the whole module is one xdist group, tests taking `api` alone included.
pytestmark = pytest.mark.xdist_group("e2e/test_cell_cycle.py")

SPEED_FACTOR = "8"
SPRAY_DEMO = {"contour_matching": False, "workpiece_id": "demo"}  # the commissioned part
SAFE_POSITION = list(Settings().safe_position)  # the server runs with the default


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory):
    """Robot simulator, glue simulator and server: three processes."""
    data = tmp_path_factory.mktemp("cell")
    with (
        simulator("server.drivers.sim.robot_sim", "--speed-factor", SPEED_FACTOR) as robot,
        simulator("server.drivers.sim.glue_sim", "--control-port", "0") as glue,
    ):
        port = free_port()
        env = {
            "ROBOT_IP": "127.0.0.1",
            "GLUE_APP_ROBOT_PORT": str(robot.port),
            "GLUE_CONTROLLER_PORT": f"tcp://127.0.0.1:{glue.port}",
            "GLUE_APP_ROBOT_COMMUNICATION_TIMEOUT": "3",
            "GLUE_APP_GLUE_SYSTEM_TIMEOUT": "2",
        }
        with server_process(port, data, env):
            yield {
                "url": f"http://127.0.0.1:{port}",
                "robot_port": robot.port,
                "glue_port": glue.port,
                "data": data,
            }


@pytest.fixture
async def api(cell) -> AsyncIterator[httpx.AsyncClient]:
    headers = admin_headers(cell["data"])
    async with httpx.AsyncClient(base_url=cell["url"], timeout=15, headers=headers) as client:
        await wait_state(client, "IDLE", allow=("INITIALIZING", "IDLE"))
        yield client


@pytest.fixture
async def robot_sim(cell) -> AsyncIterator[JsonRpcRobot]:
    """A second client of the robot simulator, for its sim.* inspection methods."""
    robot = JsonRpcRobot("127.0.0.1", cell["robot_port"], timeout=3)
    await robot.connect()
    yield robot
    await robot.close()


@pytest.fixture
async def glue_reader(cell) -> AsyncIterator[ModbusGlueDispenser]:
    glue = ModbusGlueDispenser.tcp("127.0.0.1", cell["glue_port"], timeout=2)
    await glue.connect()
    yield glue
    await glue.close()


async def wait_state(
    client: httpx.AsyncClient, state: str, timeout: float = 30, allow: tuple[str, ...] | None = None
) -> dict:
    async with asyncio.timeout(timeout):
        while True:
            snapshot = (await client.get("/state")).json()
            if snapshot["state"] == state:
                return snapshot
            if allow is not None:
                assert snapshot["state"] in allow, snapshot
            await asyncio.sleep(0.02)


async def messages_until(ws, predicate, timeout: float = 30) -> list[dict]:
    received = []
    async with asyncio.timeout(timeout):
        while True:
            message = json.loads(await ws.recv())
            received.append(message)
            if predicate(message):
                return received


def ws_url(cell) -> str:
    return cell["url"].replace("http", "ws") + "/ws"


async def test_start_drives_a_full_cycle_seen_state_by_state(cell, api, robot_sim) -> None:
    await robot_sim.call("sim.clearPath")
    async with websockets.connect(
        ws_url(cell), additional_headers=admin_headers(cell["data"])
    ) as ws:
        snapshot = json.loads(await ws.recv())
        assert snapshot["type"] == "snapshot" and snapshot["state"] == "IDLE"
        response = await api.post("/start")  # contour matching: find the part, then spray it
        assert response.status_code == 202, response.text
        messages = await messages_until(
            ws, lambda m: m["type"] == "state_changed" and m["new_state"] == "IDLE"
        )
    states = [m["new_state"] for m in messages if m["type"] == "state_changed"]
    assert states == ["EXECUTING_TRAJECTORY", "IDLE"]
    assert messages[-1]["event"] == "OPERATION_COMPLETED"
    progress = [m for m in messages if is_waypoint(m)]
    assert [m["waypoint"] for m in progress] == list(range(1, len(progress) + 1))
    assert progress[-1]["fraction"] == 1.0
    assert [m["seq"] for m in messages] == list(
        range(snapshot["seq"] + 1, snapshot["seq"] + 1 + len(messages))
    )
    # The robot simulator really executed the planned path, in order.
    trajectory = (await api.get("/trajectory")).json()
    assert trajectory["workpieces"][0]["workpiece_id"] == "demo"
    planned = [w["pose"] for w in trajectory["planned_path"]]
    executed = [
        s["end"]
        for s in await robot_sim.call("sim.getExecutedPath")
        if s["method"] == "moveL" and not s["interrupted"]
    ]
    # The run's first step is the move to the safe position, then the planned path.
    assert executed[0] == pytest.approx(SAFE_POSITION, abs=0.01)
    executed = executed[1:]
    assert len(executed) >= len(planned)
    for reached, target in zip(executed, planned, strict=False):
        assert reached == pytest.approx(target, abs=0.01)


async def test_estop_mid_run_halts_the_devices_then_reset_returns_to_idle(
    cell, api, robot_sim, glue_reader
) -> None:
    assert (await api.post("/start", json=SPRAY_DEMO)).status_code == 202
    async with asyncio.timeout(20):  # wait until glue is flowing
        while not (await glue_reader.read_status()).valve_open:
            await asyncio.sleep(0.01)
    stops_before = (await robot_sim.call("sim.stats"))["stop_count"]
    response = await api.post("/estop", json={"reason": "test: hand in the cell"})
    assert response.status_code == 202 and response.json()["state"] == "ERROR"
    status = await glue_reader.read_status()
    assert status.valve_open is False
    stats = await robot_sim.call("sim.stats")
    assert stats["stop_count"] > stops_before
    assert await robot_sim.is_moving() is False
    snapshot = (await api.get("/state")).json()
    assert snapshot["state"] == "ERROR"
    assert snapshot["stop_reason"]["code"] == "EMERGENCY_STOP"
    assert "hand in the cell" in snapshot["stop_reason"]["message"]
    assert snapshot["available_commands"] == ["estop", "reset"]
    refused = await api.post("/start", json=SPRAY_DEMO)
    assert refused.status_code == 409
    reset = await api.post("/reset")
    assert reset.status_code == 202 and reset.json()["state"] == "IDLE"
    assert (await api.get("/state")).json()["stop_reason"] is None


async def test_pause_then_resume_finishes_the_same_run(cell, api, glue_reader) -> None:
    async with websockets.connect(
        ws_url(cell), additional_headers=admin_headers(cell["data"])
    ) as ws:
        await ws.recv()
        start = await api.post("/start", json=SPRAY_DEMO)
        run_id = start.json()["event_id"]
        await messages_until(ws, lambda m: m["type"] == "progress" and m.get("waypoint") == 3)
        assert (await api.post("/pause")).json()["state"] == "PAUSED"
        await asyncio.sleep(0.5)  # holds where it stopped
        held = (await api.get("/state")).json()
        assert held["state"] == "PAUSED"
        assert (await glue_reader.read_status()).valve_open is False
        held_at = held["operation"]["progress"]["waypoint"]
        await asyncio.sleep(0.3)
        assert (await api.get("/state")).json()["operation"]["progress"]["waypoint"] == held_at
        assert (await api.post("/resume")).json()["state"] == "EXECUTING_TRAJECTORY"
        rest = await messages_until(
            ws, lambda m: m["type"] == "state_changed" and m["new_state"] == "IDLE"
        )
    waypoints = [m["waypoint"] for m in rest if is_waypoint(m)]
    # Continued from the hold, not restarted: no waypoint before the pause comes again.
    assert min(waypoints) > 3 and waypoints == sorted(set(waypoints))
    total = next(m["total"] for m in rest if m["type"] == "progress" and "total" in m)
    assert [w for w in waypoints if w > held_at] == list(range(held_at + 1, total + 1))
    assert {m["run_id"] for m in rest if m["type"] == "progress"} == {run_id}
    assert rest[-1]["event"] == "OPERATION_COMPLETED"


async def test_health_reports_each_device(api) -> None:
    health = (await api.get("/health")).json()
    assert health["status"] == "ok"
    for name in ("robot", "glue", "camera"):
        assert health["devices"][name]["connected"] is True
        assert health["devices"][name]["last_rtt_ms"] is not None
    assert health["devices"]["glue"]["temperature_c"] is not None


def test_the_server_log_is_readable(cell) -> None:
    """The spec's log format in the rotating file; fault lines carry their event id."""
    text = Path(cell["data"], "logs", "glue_cell.log").read_text()
    assert "EXECUTING_TRAJECTORY" in text and "Traceback" not in text
    line = re.compile(
        r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d{3} \[(DEBUG|INFO|WARNING|ERROR|CRITICAL)\] "
    )
    lines = text.splitlines()
    assert all(line.match(entry) for entry in lines if entry and not entry.startswith(" "))
    faults = [
        entry
        for entry in lines
        if "[ERROR] server.core.worker.state_changes: fault EMERGENCY_STOP" in entry
    ]
    assert faults and all(re.search(r"\(\w{6}-\d{6}\)", entry) for entry in faults)
    # The specification's Error: and Context: lines, indented under the fault's line.
    first = lines.index(faults[0])
    assert lines[first + 1].startswith("  Error: emergency stop by ")
    # The e-stop came mid-run: the context names the run it stopped, not None.
    assert lines[first + 2].startswith("  Context: {'operation': 'trajectory', 'run_id': ")
    assert "'workpiece_id': " in lines[first + 2]
