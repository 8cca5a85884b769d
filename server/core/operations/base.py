"""What an operation is: a plain async function of an OperationContext.

An operation does the work of one operational state (spray a path, calibrate,
create a workpiece) and returns an `OperationResult`, or raises. It never
touches the state machine: the worker turns its return into
OPERATION_COMPLETED and its exception into OPERATION_FAILED. That is what
makes operations replaceable: an integrator can hand in the methods of an
existing application as operations without touching the core.

An operation speaks to the rest of the cell only through its context: its
progress (`ctx.report`), the path it planned (`ctx.publish_plan`) and where it
may hold for a pause (`ctx.gate.checkpoint`).
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any, Final, Protocol

from server.core.infra.clock import SYSTEM_CLOCK, Clock
from server.core.operations.frames import LatestFrame
from server.drivers.base import Camera, GlueDispenser, Robot
from server.settings.model import Settings
from server.storage import CellStores

# The names a run's progress is told in, on every transport (the WebSocket, MQTT's
# `progress`, OPC UA's CellState, GET /state's operation.progress, the journal):
PROGRESS_FIELDS: Final = (
    "step",  # what the operation is doing, in words
    "waypoint",  # the waypoint reached, counted from 1 (a spray run)
    "views",  # the chessboard views collected (a camera calibration)
    "total",  # how many waypoints, or views, there are
    "fraction",  # how far the run is, 0..1
    "workpiece_id",  # the library part being sprayed or stored
)


@dataclass(frozen=True, slots=True)
class OperationWarning:
    """A condition the technician should hear of although the operation succeeded."""

    code: str
    message: str


@dataclass(frozen=True, slots=True)
class OperationResult:
    """What a successful operation hands back: its JSON-able result and its warnings."""

    data: dict[str, Any] = field(default_factory=dict)
    warnings: tuple[OperationWarning, ...] = ()
    # A spray run's whole inspection (server/quality/): journaled with the run's end, in
    # its own table; the data carries only its summary.
    inspection: dict[str, Any] | None = None

    def as_dict(self) -> dict[str, Any]:
        """The result as /state and the journal show it (warnings beside the data)."""
        if not self.warnings:
            return dict(self.data)
        warnings = [{"code": w.code, "message": w.message} for w in self.warnings]
        return {**self.data, "warnings": warnings}


@dataclass(frozen=True, slots=True)
class PlannedPath:
    """The path a run will follow, as the HMI draws it: waypoints and the parts they spray."""

    waypoints: list[dict[str, Any]]
    workpieces: list[dict[str, Any]]


class RunListener(Protocol):
    """Who hears a running operation: the worker's run supervisor, or nobody."""

    def on_progress(self, progress: dict[str, Any]) -> None: ...

    def on_plan(self, plan: PlannedPath) -> None: ...


class QuietListener:
    """For operations run outside the machine (commissioning, tests): hears nothing."""

    def on_progress(self, progress: dict[str, Any]) -> None:
        pass

    def on_plan(self, plan: PlannedPath) -> None:
        pass


class PauseGate:
    """Lets a running operation hold where it is while the cell is PAUSED.

    The worker closes the gate on PAUSE and opens it on RESUME. An operation
    marks the stretches that command the devices as *steps* (`async with
    gate.step():`); inside one it runs each move in an `interruption()`, which
    `pause()` cancels on the spot (a move that was about to send its motion
    command never sends it; one under way makes the driver send `stop`); the
    operation then stops the robot where it is, closes the valve and leaves the
    step. `settled()` is what the worker waits for before it reports PAUSED: no
    step in progress, so nothing the operation sent can still move the arm or
    open the valve. Outside a step an operation commands
    nothing, so a pause there is settled at once; the next step waits at the
    gate. `checkpoint()` is the plain form: hold here while paused.
    """

    def __init__(self, clock: Clock = SYSTEM_CLOCK) -> None:
        self._clock = clock
        self._open = asyncio.Event()
        self._open.set()
        self._in_task: set[Interruption] = set()
        self._no_step = asyncio.Event()
        self._no_step.set()
        self._steps = 0
        self.holding = False  # the operation is waiting at the gate
        self._paused_at: float | None = None
        self._paused_total = 0.0

    @property
    def paused(self) -> bool:
        return not self._open.is_set()

    def pause(self) -> None:
        if self._paused_at is None:
            self._paused_at = self._clock.monotonic()
        self._open.clear()
        for stretch in list(self._in_task):
            stretch.interrupt()

    def resume(self) -> None:
        if self._paused_at is not None:
            self._paused_total += self._clock.monotonic() - self._paused_at
            self._paused_at = None
        self._open.set()

    def paused_seconds(self) -> float:
        """Time spent paused so far; processing_timeout does not count it."""
        now = self._clock.monotonic()
        current = now - self._paused_at if self._paused_at is not None else 0.0
        return self._paused_total + current

    def interruption(self) -> Interruption:
        """A stretch of the current task that a pause interrupts on the spot (see Interruption)."""
        return Interruption(self._in_task)

    @property
    def in_step(self) -> bool:
        """A step is in progress: the run may be commanding the devices."""
        return self._steps > 0

    async def settled(self) -> None:
        """Return once no step is in progress: the run commands nothing until the gate opens."""
        await self._no_step.wait()

    async def checkpoint(self, on_hold: Callable[[], Awaitable[None]] | None = None) -> bool:
        """Wait here while paused; run `on_hold` (e.g. close the valve) first. True if it held."""
        if not self.paused:
            return False
        if on_hold is not None:
            await on_hold()
        self.holding = True
        try:
            await self._open.wait()
        finally:
            self.holding = False
        return True

    @contextlib.asynccontextmanager
    async def step(
        self, on_hold: Callable[[], Awaitable[None]] | None = None
    ) -> AsyncIterator[None]:
        """A stretch that commands the devices: entered once the gate is open, and
        counted until it ends, so `settled()` waits for it (see the class doc)."""
        while await self.checkpoint(on_hold):
            pass  # paused again between the resume and this task running
        self._steps += 1
        self._no_step.clear()
        try:
            yield
        finally:
            self._steps -= 1
            if self._steps == 0:
                self._no_step.set()


class Interruption:
    """`async with gate.interruption() as it:` a pause cancels this task inside the block,
    and the block ends as if its work had returned, with `it.interrupted` set.

    Why not a task per move: a move that answers at once would
    cost its run a task and a loop turn for nothing. The cancellation is the pause's
    own, told apart from any other by the task's cancel count, as asyncio.timeout
    does: a cancel from outside (the run cancelled, a timeout) that lands too is
    never swallowed, it goes on up.
    """

    __slots__ = ("_cancelling", "_registry", "_task", "interrupted")

    def __init__(self, registry: set[Interruption]) -> None:
        self._registry = registry
        self._task: asyncio.Task[Any] | None = None
        self._cancelling = 0
        self.interrupted = False

    async def __aenter__(self) -> Interruption:
        task = asyncio.current_task()
        assert task is not None, "an interruption belongs to a task"
        self._task, self._cancelling = task, task.cancelling()
        self._registry.add(self)
        return self

    async def __aexit__(self, exc_type: type[BaseException] | None, *_: object) -> bool:
        self._registry.discard(self)
        if not self.interrupted or self._task is None:
            return False
        remaining = self._task.uncancel()  # the pause's cancel, delivered or not, is spent
        return exc_type is asyncio.CancelledError and remaining <= self._cancelling

    def interrupt(self) -> None:
        """Cancel the task where it waits inside the block (the pause does, synchronously)."""
        if not self.interrupted and self._task is not None:
            self.interrupted = True
            self._task.cancel()


@dataclass
class OperationContext:
    """Everything an operation may use; nothing else reaches it."""

    robot: Robot
    glue: GlueDispenser
    camera: Camera
    settings: Settings
    stores: CellStores
    params: dict[str, Any]  # the request's parameters (the event's payload as a dict)
    listener: RunListener = field(default_factory=QuietListener)
    gate: PauseGate = field(default_factory=PauseGate)
    run_id: str = ""
    operation: str = ""  # its name (trajectory, create_workpiece, ...), as the worker runs it
    # Where the frames measured on are kept for the HMI (the worker's; a throwaway otherwise).
    frames: LatestFrame = field(default_factory=LatestFrame)
    clock: Clock = SYSTEM_CLOCK

    def report(self, progress: dict[str, Any]) -> None:
        """Progress for the HMI, the plant and the journal, in PROGRESS_FIELDS' names."""
        self.listener.on_progress(progress)

    def publish_plan(
        self, waypoints: list[dict[str, Any]], workpieces: list[dict[str, Any]]
    ) -> None:
        """The path this run will follow, before the robot moves (GET /trajectory)."""
        self.listener.on_plan(PlannedPath(waypoints, workpieces))


Operation = Callable[[OperationContext], Awaitable[OperationResult]]
