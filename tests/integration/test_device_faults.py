"""Device faults during a run, through the whole server and the real protocol
clients: every one ends in ERROR with the glue valve closed and the robot
stopped, names the fault, and reset waits until the fault has cleared."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator

import pytest

from tests.rig import Rig, assert_safe, open_rig


@pytest.fixture(scope="module")
def cell_data(tmp_path_factory: pytest.TempPathFactory):
    """One data directory for the module: the simulated cell is commissioned once."""
    return tmp_path_factory.mktemp("cell")


@pytest.fixture
async def rig(cell_data) -> AsyncIterator[Rig]:
    async with open_rig(cell_data) as running:
        yield running


async def test_robot_connection_dropped(rig: Rig) -> None:
    await rig.start_spraying()
    rig.robot.inject_fault("drop", duration=1.5)  # and refuse reconnection for a while
    snapshot = await assert_safe(rig, "robot")
    assert snapshot["stop_reason"]["code"] == "COMM_LOST"
    assert rig.glue.valve_open is False
    refused = await rig.reset()
    assert refused.status_code == 409 and "robot" in refused.json()["message"]
    await asyncio.sleep(1.6)
    async with asyncio.timeout(10):  # the client reconnects by itself; reset then succeeds
        while (await rig.reset()).status_code != 202:
            await asyncio.sleep(0.2)
    await rig.wait_state("IDLE")


async def test_robot_stalled(rig: Rig) -> None:
    await rig.start_spraying()
    rig.robot.inject_fault("stall")
    snapshot = await assert_safe(rig, "robot")
    assert "robot" in snapshot["stop_reason"]["message"]
    assert rig.glue.valve_open is False
    refused = await rig.reset()
    assert refused.status_code == 409 and "robot: no answer in time" in refused.json()["message"]
    rig.robot.clear_faults()
    assert (await rig.reset()).status_code == 202


async def test_robot_silent_while_idle_is_found_by_the_heartbeat(cell_data) -> None:
    async with open_rig(cell_data, robot_heartbeat_interval=0.1) as rig:
        async with asyncio.timeout(10):  # the homing move done: nothing is asked of the robot
            while rig.robot.is_moving:
                await asyncio.sleep(0.05)
        await asyncio.sleep(0.3)
        rig.robot.inject_fault("stall")
        snapshot = await assert_safe(rig, "robot")
        assert snapshot["stop_reason"]["code"] == "NO_ANSWER"
        assert "check the robot controller" in snapshot["stop_reason"]["recommended_action"]
        allowed = (await rig.api.get("/operations/reset/allowed")).json()
        assert not allowed["allowed"] and "robot: no answer" in allowed["reason"]
        assert (await rig.reset()).status_code == 409
        rig.robot.clear_faults()
        async with asyncio.timeout(10):  # the next heartbeat is answered
            while (await rig.reset()).status_code != 202:
                await asyncio.sleep(0.1)
        await rig.wait_state("IDLE")


async def test_robot_refuses_the_next_command(rig: Rig) -> None:
    await rig.start_spraying()
    rig.robot.inject_fault("fail_next")
    snapshot = await assert_safe(rig, "robot")
    assert "1002" in snapshot["stop_reason"]["message"]
    assert rig.glue.valve_open is False
    assert (await rig.reset()).status_code == 202  # a refused command is not a lasting fault


async def test_dispenser_silent(rig: Rig) -> None:
    await rig.start_spraying()
    stops = rig.robot.stop_received_count
    rig.glue.inject_no_reply()
    snapshot = await assert_safe(rig, "glue")
    # Silent while spraying: the valve could not be confirmed closed (glue supervision).
    assert snapshot["stop_reason"]["code"] in ("VALVE_UNCONFIRMED", "NO_REPLY", "DEVICE_FAULT")
    assert rig.robot.stop_received_count > stops
    refused = await rig.reset()
    assert refused.status_code == 409 and "glue" in refused.json()["message"]
    rig.glue.clear_faults()
    accepted = await rig.reset()
    assert accepted.status_code == 202, accepted.json()
    assert rig.glue.valve_open is False  # the close lost during the silence is re-asserted


async def test_dispenser_silent_with_the_valve_open_stops_at_once(cell_data) -> None:
    """Within glue_link_timeout, not after glue_system_timeout (its real default, 15 s)."""
    async with open_rig(cell_data, glue_system_timeout=15.0) as rig:
        await rig.start_spraying()
        stops = rig.robot.stop_received_count
        rig.glue.inject_no_reply()
        snapshot = await assert_safe(rig, "glue")  # waits far less than 15 s
        assert snapshot["stop_reason"]["code"] == "VALVE_UNCONFIRMED"
        assert "the valve could not be confirmed closed" in snapshot["stop_reason"]["message"]
        assert "check the glue valve is closed" in snapshot["stop_reason"]["recommended_action"]
        assert rig.robot.stop_received_count > stops
        rig.glue.clear_faults()
        async with asyncio.timeout(10):
            while (await rig.reset()).status_code != 202:
                await asyncio.sleep(0.2)
        assert rig.glue.valve_open is False


@pytest.mark.parametrize(
    ("inject", "code", "words"),
    [
        (lambda glue: glue.force_flow(5.0), "FLOW_DEVIATION", "off its setpoint"),
        (lambda glue: glue.force_pressure(100.0), "PRESSURE_OUT_OF_RANGE", "20-60 PSI"),
        (lambda glue: glue.force_temperature(55.0), "TEMPERATURE_OUT_OF_RANGE", "10-40 °C"),
    ],
    ids=["flow", "pressure", "temperature"],
)
async def test_glue_supervision_is_on_by_default(rig: Rig, inject, code: str, words: str) -> None:
    """Each within the register's range, outside the default process window."""
    await rig.start_spraying()
    inject(rig.glue)
    snapshot = await assert_safe(rig, "glue")
    assert snapshot["stop_reason"]["code"] == code
    assert words in snapshot["stop_reason"]["message"]
    assert rig.glue.valve_open is False
    rig.glue.clear_faults()
    async with asyncio.timeout(10):  # the monitor's next poll sees it cleared
        while (await rig.reset()).status_code != 202:
            await asyncio.sleep(0.1)


async def test_dispenser_alarm(rig: Rig) -> None:
    await rig.start_spraying()
    rig.glue.set_alarm("NOZZLE_BLOCKED")
    snapshot = await assert_safe(rig, "glue")
    assert "NOZZLE_BLOCKED" in snapshot["stop_reason"]["message"]
    assert rig.glue.valve_open is False
    # What the dispenser's monitoring already knows, the HMI's Reset button knows too.
    allowed = (await rig.api.get("/operations/reset/allowed")).json()
    assert not allowed["allowed"] and "glue: alarm NOZZLE_BLOCKED" in allowed["reason"]
    assert "reset" not in (await rig.state())["available_commands"]
    health = (await rig.api.get("/health")).json()["devices"]["glue"]
    assert health["active_faults"] == ["glue: alarm NOZZLE_BLOCKED"]
    refused = await rig.reset()
    assert refused.status_code == 409
    assert "glue: alarm NOZZLE_BLOCKED" in refused.json()["message"]
    rig.glue.clear_faults()
    async with asyncio.timeout(10):  # the monitor's next poll sees it cleared
        while not (await rig.api.get("/operations/reset/allowed")).json()["allowed"]:
            await asyncio.sleep(0.05)
    assert (await rig.reset()).status_code == 202


async def test_dispenser_pressure_out_of_range(rig: Rig) -> None:
    await rig.start_spraying()
    rig.glue.force_pressure(180.0)
    snapshot = await assert_safe(rig, "glue")
    assert "pressure" in snapshot["stop_reason"]["message"].lower()
    assert rig.glue.valve_open is False
    refused = await rig.reset()
    assert refused.status_code == 409 and "outside" in refused.json()["message"]
    rig.glue.clear_faults()
    assert (await rig.reset()).status_code == 202


async def test_the_pressure_window_is_a_setting(cell_data) -> None:
    async with open_rig(cell_data, glue_pressure_range_psi=(0.0, 100.0)) as rig:
        await rig.start_spraying()
        rig.glue.force_pressure(120.0)  # inside the register's range, outside this cell's window
        snapshot = await assert_safe(rig, "glue")
        assert "outside the allowed 0-100 PSI" in snapshot["stop_reason"]["message"]
        rig.glue.clear_faults()
        async with asyncio.timeout(10):
            while (await rig.reset()).status_code != 202:
                await asyncio.sleep(0.2)


async def test_camera_failure_during_an_operation(rig: Rig) -> None:
    rig.camera.inject_fault("fail")
    assert (await rig.api.post("/calibrate-robot")).status_code == 202
    snapshot = await assert_safe(rig, "camera")
    assert rig.glue.valve_open is False
    refused = await rig.reset()
    assert refused.status_code == 409 and "camera" in refused.json()["message"]
    rig.camera.clear_faults()
    assert (await rig.reset()).status_code == 202
    assert snapshot["error"]["component"] == "camera"


async def test_health_shows_the_fault_then_the_recovery(rig: Rig) -> None:
    rig.glue.inject_no_reply()
    async with asyncio.timeout(10):
        while (await rig.api.get("/health")).json()["devices"]["glue"]["connected"]:
            await asyncio.sleep(0.05)
    health = (await rig.api.get("/health")).json()
    assert health["status"] == "degraded" and health["devices"]["glue"]["last_error"]
    await rig.wait_state("ERROR")
    rig.glue.clear_faults()
    assert (await rig.reset()).status_code == 202
    async with asyncio.timeout(10):
        while not (await rig.api.get("/health")).json()["devices"]["glue"]["connected"]:
            await asyncio.sleep(0.05)
