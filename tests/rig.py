"""Tier two with real protocols: the cell server in this test's loop, reaching the
robot and glue simulators (also in this loop) through its production clients,
and the simulated camera in-process, so tests can move parts on the table and
inject faults."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Any

import httpx

from server.cell import Cell
from server.config import Settings
from server.drivers.camera import SimulatedCamera
from server.drivers.sim.glue_sim import GlueSimulator
from server.drivers.sim.robot_sim import RobotSimulator
from tests.serving import admin_headers, serve

SPRAY_DEMO = {"contour_matching": False, "workpiece_id": "demo"}
TIMEOUT = 1.0  # robot_communication_timeout and glue_system_timeout on the rig


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
        assert (await self.api.post("/start", json=SPRAY_DEMO)).status_code == 202
        async with asyncio.timeout(15):
            while not self.glue.valve_open:
                await asyncio.sleep(0.005)

    async def reset(self) -> httpx.Response:
        return await self.api.post("/reset")


@contextlib.asynccontextmanager
async def open_rig(data_path, **overrides: Any) -> AsyncIterator[Rig]:
    """Simulators, cell and HTTP client; the cell commissioned in `data_path`."""
    async with RobotSimulator(speed_factor=4) as robot, GlueSimulator() as glue:
        settings = Settings(
            robot_ip="127.0.0.1",
            robot_port=robot.port,
            glue_controller_port=f"tcp://127.0.0.1:{glue.port}",
            robot_communication_timeout=TIMEOUT,
            glue_system_timeout=TIMEOUT,
            emergency_stop_timeout=0.5,
            vision_processing_timeout=10,
            data_path=data_path,
            **overrides,
        )
        cell = Cell(settings)
        async with (
            serve(cell) as url,
            httpx.AsyncClient(base_url=url, timeout=10, headers=admin_headers(data_path)) as api,
        ):
            rig = Rig(api, cell, robot, glue)
            await rig.wait_state("IDLE")
            yield rig
