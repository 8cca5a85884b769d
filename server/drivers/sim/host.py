"""Run the robot and glue simulators on loopback, in a thread of their own.

The default run starts them here and connects to them through the production
clients, so the server's own event loop carries only what it would carry on a
real cell, and the simulated devices keep their timing while the server is busy.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Coroutine
from typing import Any, TypeVar

from server.drivers.sim.glue_sim import GlueSimulator
from server.drivers.sim.robot_sim import RobotSimulator
from server.settings.model import Settings

T = TypeVar("T")


class SimulatorHost:
    """Starts the simulators the settings ask for; `robot_port` and `glue_port` once started."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.robot: RobotSimulator | None = None
        self.glue: GlueSimulator | None = None
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(
            target=self._loop.run_forever, name="device-simulators", daemon=True
        )

    def _call(self, coroutine: Coroutine[Any, Any, T]) -> T:
        return asyncio.run_coroutine_threadsafe(coroutine, self._loop).result(timeout=30)

    def start(self) -> None:
        self._thread.start()
        settings = self.settings
        if settings.robot_simulated:
            self.robot = RobotSimulator(
                "127.0.0.1",
                0,
                workspace_min=settings.workspace_min_mm,
                workspace_max=settings.workspace_max_mm,
                home=settings.safe_position,
                speed_factor=settings.simulation_speed_factor,
            )
            self._call(self.robot.start())
        if settings.glue_simulated:
            self.glue = GlueSimulator(
                "127.0.0.1",
                0,
                device_id=settings.glue_modbus_device_id,
                speed_factor=settings.simulation_speed_factor,
            )
            self._call(self.glue.start())
        if self.robot is not None and self.glue is not None:
            # One thread runs both: the dispenser follows the robot's speed, as a real
            # speed-following dispenser wired to the robot controller does.
            self.glue.speed_source = self.robot

    def stop(self) -> None:
        for simulator in (self.robot, self.glue):
            if simulator is not None:
                self._call(simulator.stop())
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=10)
        self._loop.close()
