"""In-process fakes of the three devices, for unit tests of the core only.

They keep the Protocols' behaviour that the core relies on (a move takes
distance / speed, stop interrupts it, a cancelled move stops the arm, faults
can be injected) without any protocol underneath. Integration tests use the
real clients against the network simulators instead.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable

import numpy as np

from server.common.errors import DeviceDisconnected, DeviceTimeout
from server.drivers.base import DeviceFault, DeviceHealth, FaultListener, GlueStatus, Pose


class FakeRobot:
    def __init__(self, speed_factor: float = 50.0) -> None:
        self.health = DeviceHealth("robot")
        self.position = Pose(400.0, 0.0, 200.0)
        self.speed_factor = speed_factor
        self.moving = False
        self.stops = 0
        self.moves: list[Pose] = []
        self.failing = False
        self.stalled = False
        self.probe_delay = 0.0  # seconds get_position takes (a slow controller)
        self.sessions = 0  # link sessions begun (one per reset probe)
        self.position_reads = 0
        self._listener: FaultListener | None = None
        self._stop_event = asyncio.Event()

    def set_fault_listener(self, listener: FaultListener | None) -> None:
        self._listener = listener

    def new_session(self) -> int:
        self.sessions += 1
        return self.sessions

    def _check(self) -> None:
        if self.failing:
            raise DeviceDisconnected("robot", "connection lost")

    async def connect(self) -> None:
        self._check()
        self.health.connected = True

    async def close(self) -> None:
        self.health.connected = False

    async def move_linear(self, pose: Pose, speed: float, acceleration: float) -> None:
        self._check()
        if self.stalled:
            await asyncio.sleep(3600)
        start = self.position
        distance = math.dist(start[:3], pose[:3])
        duration = distance / speed / self.speed_factor
        self.moving = True
        self._stop_event.clear()
        try:
            stopped = False
            try:
                await asyncio.wait_for(self._stop_event.wait(), duration)
                stopped = True
            except TimeoutError:
                pass
            if not stopped:
                self.position = pose
                self.moves.append(pose)
        except asyncio.CancelledError:
            await self.stop()
            raise
        finally:
            self.moving = False

    async def move_joint(self, target: Pose, speed: float) -> None:
        await self.move_linear(target, speed, 0.0)

    async def get_position(self) -> Pose:
        self._check()
        self.position_reads += 1
        if self.probe_delay:
            await asyncio.sleep(self.probe_delay)
        return self.position

    async def is_moving(self) -> bool:
        return self.moving

    async def stop(self) -> None:
        self._check()
        self.stops += 1
        self._stop_event.set()

    def fail(self, message: str = "connection lost") -> None:
        """Simulate a dropped link: calls fail and the listener hears of it once."""
        self.failing = True
        self.health.connected = False
        if self._listener:
            self._listener(DeviceFault("robot", "COMM_LOST", message))

    def recover(self) -> None:
        self.failing = False
        self.health.connected = True


class FakeGlue:
    def __init__(self) -> None:
        self.health = DeviceHealth("glue")
        self.pressure_range_psi = (0.0, 150.0)
        self.valve_open = False
        self.valve_log: list[tuple[float, bool]] = []
        self.flow = 0.0
        self.pressure = 0.0
        self.alarms: tuple[str, ...] = ()
        self.silent = False
        self.sessions = 0  # link sessions begun (one per reset probe)
        self.drops: list[float] = []  # when waiting openings were refused (none ever wait here)
        self._listener: FaultListener | None = None

    def set_fault_listener(self, listener: FaultListener | None) -> None:
        self._listener = listener

    def new_session(self) -> int:
        self.sessions += 1
        return self.sessions

    def drop_waiting_openings(self) -> int:
        self.drops.append(time.perf_counter())
        return 0

    async def _exchange(self) -> None:
        if self.silent:
            raise DeviceTimeout("glue", "no reply")

    async def connect(self) -> None:
        await self._exchange()
        self.health.connected = True

    async def close(self) -> None:
        self.health.connected = False

    async def set_valve(self, open_: bool) -> None:
        await self._exchange()
        self.valve_open = open_
        self.valve_log.append((time.perf_counter(), open_))

    async def set_flow_rate(self, ml_per_min: float) -> None:
        await self._exchange()
        self.flow = ml_per_min

    async def set_pressure(self, psi: float) -> None:
        await self._exchange()
        self.pressure = psi

    async def read_status(self) -> GlueStatus:
        await self._exchange()
        return GlueStatus(
            self.valve_open,
            self.flow,
            self.pressure,
            self.flow if self.valve_open else 0.0,
            self.pressure,
            25.0,
            self.alarms,
        )


class FakeCamera:
    def __init__(self) -> None:
        self.health = DeviceHealth("camera")
        self.broken = False

    def set_fault_listener(self, listener: FaultListener | None) -> None:
        pass

    async def connect(self) -> None:
        self.health.connected = True

    async def close(self) -> None:
        self.health.connected = False

    async def capture(self) -> np.ndarray:
        if self.broken:
            raise DeviceDisconnected("camera", "no frame")
        return np.zeros((1080, 1920, 3), np.uint8)


class FakeClock:
    """Virtual time for unit tests: nothing waits until the test advances the clock.

    `sleep` parks the caller until `advance` moves time past its deadline, so a
    30 s budget or a 5 s alert is tested in milliseconds and never races a
    loaded machine.
    """

    def __init__(self, wall_start: float = 1_700_000_000.0) -> None:
        self._now = 0.0
        self._wall_start = wall_start
        self._sleepers: list[tuple[float, asyncio.Future[None]]] = []

    def time(self) -> float:
        return self._wall_start + self._now

    def monotonic(self) -> float:
        return self._now

    async def sleep(self, seconds: float) -> None:
        future = asyncio.get_running_loop().create_future()
        self._sleepers.append((self._now + max(seconds, 0.0), future))
        await future

    def call_later(self, seconds: float, callback: Callable[[], None]) -> asyncio.Future[None]:
        """`callback` once `advance` moves time past `seconds` from now; cancel() drops it."""
        future = asyncio.get_running_loop().create_future()
        future.add_done_callback(lambda done: None if done.cancelled() else callback())
        self._sleepers.append((self._now + max(seconds, 0.0), future))
        return future

    async def advance(self, seconds: float) -> None:
        """Let pending work reach its sleeps, move time on, and wake whoever is due."""
        await _settle()
        self._now += seconds
        due = [(at, f) for at, f in self._sleepers if at <= self._now]
        self._sleepers = [(at, f) for at, f in self._sleepers if at > self._now]
        for _, future in due:
            if not future.done():
                future.set_result(None)
        await _settle()


async def _settle(turns: int = 20) -> None:
    for _ in range(turns):
        await asyncio.sleep(0)
