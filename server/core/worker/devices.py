"""The cell's three devices as one unit: halt them safely, probe them, report health.

The safe halt (`CellDevices.safe_halt`) is the one halt there is: every fault,
pause, cancel and e-stop goes through it. The glue valve is commanded closed
first, the robot stop right behind it (both on their way at once, neither
waiting for the other's answer), each bounded by emergency_stop_timeout so a
dead device cannot hold the cell. The e-stop runs the same coroutine as a task
started at once (server/core/worker/stop.py), so its frames are written before
the stop's request goes on.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

from server.common.errors import DeviceTimeout
from server.core.infra.eager import Started, start_task, together, within
from server.drivers.base import Camera, FaultListener, GlueDispenser, Robot

log = logging.getLogger(__name__)


@dataclass
class HaltReport:
    """What the safe halt achieved, device by device."""

    valve_closed: bool
    robot_stopped: bool
    errors: list[str]


class CellDevices:
    """Robot, glue dispenser and camera, behind their Protocols."""

    def __init__(self, robot: Robot, glue: GlueDispenser, camera: Camera) -> None:
        self.robot = robot
        self.glue = glue
        self.camera = camera

    def by_name(self) -> dict[str, Robot | GlueDispenser | Camera]:
        return {"robot": self.robot, "glue": self.glue, "camera": self.camera}

    def set_fault_listener(self, listener: FaultListener | None) -> None:
        for device in self.by_name().values():
            device.set_fault_listener(listener)

    async def safe_halt(self, timeout: float, then: Callable[[], None] | None = None) -> HaltReport:
        """Close the glue valve and stop the robot now, valve first; never raises.

        Awaited in the worker's own task for a transition's HALT, or run as a task
        started at once for an e-stop (`EmergencyStops.begin`). The valve's close
        takes its first step here, at once; then the robot's stop. If the valve is
        waiting for its answer, the stop is a task started at once (its frame is
        written now, and neither waits for the other's answer); if the valve answered
        at once (nothing was waited for), the stop takes its first step here too and
        no task is made. `then` (a pause's hold) runs once both frames are written,
        before their answers.
        """
        valve = Started(within(self.glue.set_valve(False), timeout))
        stop: Started[None] | asyncio.Future[None]
        if valve.done:
            stop = Started(within(self.robot.stop(), timeout))
        else:
            stop = start_task(within(self.robot.stop(), timeout))
        try:
            if then is not None:
                then()
            valve_result = await _settled(valve)
        except BaseException:
            valve.close()
            _abandon(stop)
            raise
        try:
            stop_result = await _settled(stop)
        except BaseException:
            _abandon(stop)
            raise
        return _report(valve_result, stop_result)

    async def probe_faults(self, timeout: float) -> list[str]:
        """Ask every device for a live answer within `timeout` s in all; the faults left.

        First a new session of each link begins, so that a request sent before
        this reset (a poll or a heartbeat a stalled device swallowed) can no
        longer fault the cell once the reset has passed. `timeout`
        (reset_probe_timeout) bounds each device's whole probe, reconnecting
        included, and the devices are probed at once: a dead device costs the
        reset `timeout`, not its communication timeout.
        """
        self.robot.new_session()
        self.glue.new_session()

        async def ask(name: str) -> str | None:
            device = self.by_name()[name]
            if not device.health.connected:  # never came up, or the link was lost
                await device.connect()
            if name == "robot":
                await self.robot.get_position()
            elif name == "glue":
                return await self._probe_glue()
            else:
                await self.camera.capture()
            return None

        if (warming := getattr(self.camera, "warmed_up", None)) is not None:
            await warming()  # the simulated camera's first frame: outside the probe's timer

        async def probe(name: str) -> str | None:
            try:
                return await within(ask(name), timeout)  # the timer only if it waits
            except asyncio.CancelledError:
                raise
            except TimeoutError:
                return f"{name}: no answer in time (reset_probe_timeout {timeout:g} s)"
            except DeviceTimeout as exc:
                return f"{name}: no answer in time ({str(exc).removeprefix(name + ': ')})"
            except Exception as exc:
                return f"{name}: {_describe(exc)}"

        results = await together([probe(name) for name in self.by_name()])
        return [fault for fault in results if fault]

    async def _probe_glue(self) -> str | None:
        """Re-assert the valve closed (a close lost in a fault must not linger), then check."""
        await self.glue.set_valve(False)
        status = await self.glue.read_status()
        low, high = self.glue.pressure_range_psi
        if status.valve_open:
            return "glue: the valve still reads open after a close command"
        if status.alarms:
            return f"glue: alarm {', '.join(status.alarms)}"
        # The valve is closed now, so only the high limit applies (the low one guards
        # spraying: a supply at rest between runs is no fault).
        if status.pressure_psi > high:
            return f"glue: pressure {status.pressure_psi:.1f} PSI outside {low:g}..{high:g} PSI"
        # Whatever else the driver's own supervision sees in this reading (a temperature
        # outside its window): the probe replaces what facts knew, so it must say so.
        persisting = self.glue.health.active_faults
        return "; ".join(persisting) if persisting else None

    def health(self) -> dict[str, dict[str, Any]]:
        """Each device's connection state, last round-trip and last error."""
        return {
            name: {
                "connected": device.health.connected,
                "last_rtt_ms": device.health.last_rtt_ms,
                "last_error": device.health.last_error,
                "last_ok_at": device.health.last_ok_at,
                "active_faults": list(device.health.active_faults),
                **device.health.details,
            }
            for name, device in self.by_name().items()
        }

    async def connect(self, name: str, timeout: float) -> None:
        """Connect one device within `timeout` (TimeoutError or DeviceError otherwise)."""
        await within(self.by_name()[name].connect(), timeout)

    async def close(self) -> None:
        await asyncio.gather(
            *(device.close() for device in self.by_name().values()), return_exceptions=True
        )


async def _settled(command: Awaitable[None]) -> BaseException | None:
    """The exception a halt command ended with, or None when it succeeded.

    A cancellation of the command itself (a stop task cancelled by someone else)
    is its failure; one of the awaiting task (the worker shutting down) goes on up.
    """
    try:
        await command
    except asyncio.CancelledError as exc:
        task = asyncio.current_task()
        if task is not None and task.cancelling():
            raise
        return exc
    except Exception as exc:
        return exc
    return None


def _abandon(command: Started[None] | asyncio.Future[None]) -> None:
    if isinstance(command, Started):
        command.close()
    else:
        command.cancel()


def _report(valve_result: object, stop_result: object) -> HaltReport:
    """What the halt achieved, from each command's result or exception; errors logged."""
    errors = [
        f"{name}: {_describe(result)}"
        for name, result in (("glue valve close", valve_result), ("robot stop", stop_result))
        if isinstance(result, BaseException)
    ]
    for error in errors:
        log.error("safe halt: %s failed", error)
    return HaltReport(
        valve_closed=not isinstance(valve_result, BaseException),
        robot_stopped=not isinstance(stop_result, BaseException),
        errors=errors,
    )


def _describe(exc: BaseException) -> str:
    if isinstance(exc, TimeoutError):
        return "no answer in time"
    return str(exc) or type(exc).__name__
