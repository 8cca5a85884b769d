"""Start-up, homing and jogging: the robot's moves and device links made outside operations.

Bringing the devices up happens once, as the worker starts; the move to the
safe position on the `home` command, a jog's step on `jog` (both in IDLE). They
run as one background *activity* at a time, cancelled when the cell leaves
IDLE (CANCEL_HOMING) so a move can never outlive the state that started it.
Faults found here are posted like any device fault and decided by the worker.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable, Coroutine
from typing import Any

from server.core.machine.transitions import READINESS_EVENTS, Event
from server.core.worker.devices import CellDevices
from server.drivers.base import DeviceFault, Pose
from server.settings.model import Settings

log = logging.getLogger(__name__)

PostReady = Callable[[Event, str], None]
PostFault = Callable[[DeviceFault], None]


# The activities that move the robot (the others only bring device links up).
MOVES = ("homing", "jog", "purge")


class Activities:
    """Device start-up and the move to the safe position; one at a time."""

    def __init__(
        self,
        settings: Settings,
        devices: CellDevices,
        halt: Callable[[], Awaitable[None]],
        post_ready: PostReady,
        post_fault: PostFault,
    ) -> None:
        self.settings = settings
        self.devices = devices
        self._halt = halt
        self._post_ready = post_ready
        self._post_fault = post_fault
        self._task: asyncio.Task[None] | None = None
        self.moves_started = 0  # homing and jog moves so far: a pose read across one is stale

    def device_timeouts(self) -> dict[str, float]:
        return {
            "robot": self.settings.robot_communication_timeout,
            "glue": self.settings.glue_system_timeout,
            "camera": self.settings.vision_processing_timeout,
        }

    def bring_up(self, interruption: str | None) -> None:
        """Connect, halt and report every device (in the background)."""
        self._replace(self._bring_up_devices(interruption), "device-start-up")

    def go_home(self) -> None:
        """Send the robot to its safe position (in the background)."""
        self._replace(self._go_to_safe_position(), "homing")

    def jog(self, target: Pose) -> None:
        """Move the robot to `target` (one jog step, checked by the caller) at jog speed."""
        self._replace(self._jog_to(target), "jog")

    def purge(self, run: Coroutine[Any, Any, None]) -> None:
        """Run a purge of the glue line (server/core/worker/purging.py) as the activity."""
        self._replace(run, "purge")

    @property
    def purging(self) -> bool:
        """Whether a purge is under way (its valve may be open outside a run)."""
        task = self._task
        return task is not None and not task.done() and task.get_name() == "purge"

    @property
    def moving(self) -> bool:
        """Whether a move to the safe position or a jog is still under way."""
        task = self._task
        return task is not None and not task.done() and task.get_name() in MOVES

    async def cancel(self) -> None:
        """Stop the activity and wait (bounded) for the robot's stop to be answered.

        Why wait: an unanswered stop could otherwise stop the next move.
        """
        task, self._task = self._task, None
        if task is not None and not task.done():
            task.cancel()
            await asyncio.wait({task}, timeout=self.settings.emergency_stop_timeout)

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)

    def _replace(self, activity: Coroutine[Any, Any, None], name: str) -> None:
        if self._task is not None and not self._task.done():
            self._task.cancel()  # e.g. a start-up still connecting after an early fault
        if name in MOVES:
            self.moves_started += 1
        self._task = asyncio.create_task(activity, name=name)

    async def _bring_up_devices(self, interruption: str | None) -> None:
        """Connect every device, close the valve and stop the robot, then report.

        The halt comes first on every start: whatever the last run left behind,
        nothing sprays or moves until the machine says so. After an interruption
        the fault is posted before any READY, so the cell cannot reach IDLE by itself.
        """
        timeouts = self.device_timeouts()
        took: dict[str, float] = {}

        async def connect(name: str) -> None:
            connecting = time.perf_counter()
            try:
                await self.devices.connect(name, timeouts[name])
            finally:
                took[name] = time.perf_counter() - connecting

        results = await asyncio.gather(
            *(connect(name) for name in timeouts), return_exceptions=True
        )
        log.info(  # each on its own: the slowest sets when the cell can be ready
            "start-up: devices connected in %s",
            ", ".join(f"{name} {took[name]:.3f} s" for name in timeouts if name in took),
        )
        await self._halt()
        if interruption is not None:
            self._post_fault(DeviceFault("system", "INTERRUPTED", interruption))
        ready_event = {device: event for event, device in READINESS_EVENTS.items()}
        for name, result in zip(timeouts, results, strict=True):
            if isinstance(result, asyncio.CancelledError):
                raise result
            if isinstance(result, BaseException):
                reason = "no answer" if isinstance(result, TimeoutError) else str(result)
                self._post_fault(
                    DeviceFault(
                        name,
                        "DEVICE_UNAVAILABLE",
                        f"{name} did not come up within {timeouts[name]:g} s: {reason}",
                    )
                )
            else:
                self._post_ready(ready_event[name], name)

    async def _go_to_safe_position(self) -> None:
        settings = self.settings
        try:
            # Not wait_for: on Python 3.11 it loses a cancel that lands as the move ends
            # (see operations/safe_position.py), and the home move is cancelled on a stop.
            async with asyncio.timeout(settings.safe_position_timeout):
                await self.devices.robot.move_linear(
                    Pose.from_sequence(settings.safe_position),
                    settings.travel_speed_mm_s,
                    settings.acceleration_mm_s2,
                )
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            reason = "no answer in time" if isinstance(exc, TimeoutError) else str(exc)
            self._post_fault(
                DeviceFault(
                    "robot",
                    "SAFE_POSITION_FAILED",
                    f"robot could not reach its safe position: {reason}",
                )
            )

    async def _jog_to(self, target: Pose) -> None:
        """One jog step; a failure is a fault like any other (ERROR, valve closed first).

        No time limit of its own: the driver bounds every move by its expected
        duration plus robot_communication_timeout.
        """
        settings = self.settings
        try:
            await self.devices.robot.move_linear(
                target, settings.jog_speed_mm_s, settings.acceleration_mm_s2
            )
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            self._post_fault(
                DeviceFault("robot", "JOG_FAILED", f"the robot's jog step failed: {exc}")
            )
