"""Device faults during a run, through the whole server and the real protocol
clients: every one ends in ERROR with the glue valve closed and the robot
stopped, names the fault, and reset waits until the fault has cleared."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from dataclasses import dataclass

import httpx
import pytest

from server.cell import Cell
from server.config import Settings
from server.drivers.camera import SimulatedCamera
from server.drivers.sim.glue_sim import GlueSimulator
from server.drivers.sim.robot_sim import RobotSimulator
from tests.serving import serve

TIMEOUT = 1.0  # robot_communication_timeout and glue_system_timeout in these tests


@dataclass
class Rig:
    api: httpx.AsyncClient
    cell: Cell
    robot: RobotSimulator
    glue: GlueSimulator

    @property
    def camera(self) -> SimulatedCamera:
        return self.cell.devices.camera  # type: ignore[return-value]

    async def state(self) -> dict:
        return (await self.api.get("/state")).json()

    async def wait_state(self, state: str, timeout: float = 15) -> dict:
        async with asyncio.timeout(timeout):
            while (snapshot := await self.state())["state"] != state:
                await asyncio.sleep(0.01)
        return snapshot

    async def start_spraying(self) -> None:
        assert (await self.api.post("/start", json={"contour_matching": False})).status_code == 202
        async with asyncio.timeout(15):
            while not self.glue.valve_open:
                await asyncio.sleep(0.005)

    async def reset(self) -> httpx.Response:
        return await self.api.post("/reset")


@pytest.fixture
async def rig() -> AsyncIterator[Rig]:
    async with RobotSimulator(speed_factor=4) as robot, GlueSimulator() as glue:
        settings = Settings(
            robot_ip="127.0.0.1",
            robot_port=robot.port,
            glue_controller_port=f"tcp://127.0.0.1:{glue.port}",
            robot_communication_timeout=TIMEOUT,
            glue_system_timeout=TIMEOUT,
            emergency_stop_timeout=0.5,
            vision_processing_timeout=10,
        )
        cell = Cell(settings)
        async with serve(cell) as url, httpx.AsyncClient(base_url=url, timeout=10) as api:
            rig = Rig(api, cell, robot, glue)
            await rig.wait_state("IDLE")
            yield rig


async def assert_safe(rig: Rig, component: str) -> dict:
    """ERROR, the fault named, the valve closed and the robot still."""
    snapshot = await rig.wait_state("ERROR", timeout=TIMEOUT * 3 + 5)
    assert snapshot["stop_reason"]["component"] == component, snapshot
    async with asyncio.timeout(TIMEOUT * 3):
        while rig.robot.is_moving:
            await asyncio.sleep(0.01)
    return snapshot


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
    assert snapshot["stop_reason"]["code"] in ("NO_REPLY", "DEVICE_FAULT")
    assert rig.robot.stop_received_count > stops
    refused = await rig.reset()
    assert refused.status_code == 409 and "glue" in refused.json()["message"]
    rig.glue.clear_faults()
    assert (await rig.reset()).status_code == 202
    assert rig.glue.valve_open is False  # the close lost during the silence is re-asserted


async def test_dispenser_alarm(rig: Rig) -> None:
    await rig.start_spraying()
    rig.glue.set_alarm("NOZZLE_BLOCKED")
    snapshot = await assert_safe(rig, "glue")
    assert "NOZZLE_BLOCKED" in snapshot["stop_reason"]["message"]
    assert rig.glue.valve_open is False
    refused = await rig.reset()
    assert refused.status_code == 409
    assert "glue: alarm NOZZLE_BLOCKED" in refused.json()["message"]
    rig.glue.clear_faults()
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
