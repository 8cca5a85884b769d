"""Running operations: start one for an operational state, hear its progress, end it.

One run at a time. A run starts with the transition into an operational state
(START_RUN), lives across EXECUTING_TRAJECTORY and PAUSED (its pause gate is
closed by HOLD, which waits until the run holds, and opened by OPEN_GATE), and
ends with the transition out (RECORD_RUN_END, CANCEL_RUN). Its outcome reaches
the machine only as an OPERATION_COMPLETED or OPERATION_FAILED event posted
back to the worker, so every change of state stays in the worker's loop.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from server.core.infra.bus import Bus
from server.core.infra.clock import Clock
from server.core.machine.events import (
    Payload,
    RunCompletedPayload,
    RunFailedPayload,
)
from server.core.machine.transitions import Event
from server.core.operations.base import (
    Operation,
    OperationContext,
    OperationResult,
    PauseGate,
    PlannedPath,
)
from server.core.operations.frames import LatestFrame
from server.core.operations.leash import Leash, leashed
from server.core.operations.safe_position import move_to_safe_position
from server.core.worker.alerts import Alerts
from server.core.worker.context import MachineContext, RunningOperation
from server.core.worker.devices import CellDevices
from server.core.worker.recorder import Recorder
from server.core.worker.supervision import RunOutcome, as_result, supervise
from server.settings.model import Settings
from server.storage import CellStores

log = logging.getLogger(__name__)

# How a run ended, by the event that ended it (anything else: it failed).
RUN_OUTCOME = {Event.OPERATION_COMPLETED: "completed", Event.CANCEL_REQUESTED: "cancelled"}
PostOutcome = Callable[[Event, Payload], None]


@dataclass(frozen=True, slots=True)
class RunEnded:
    """How a run ended, as its listeners hear it (the metrics, the webhooks).

    `state` is the state the run ended in (the operation's own, or PAUSED):
    the listeners are told before the state changes.
    """

    run_id: str
    operation: str
    outcome: str  # completed, cancelled or failed
    seconds: float
    state: str
    result: dict[str, Any] | None
    error: str | None
    workpieces: int
    params: dict[str, Any] = field(default_factory=dict)  # what the run was started with


class PauseNotHeld(Exception):
    """A pause whose hold was not confirmed: the pause is refused and the cell stops."""

    def __init__(self, component: str, problems: list[str]) -> None:
        self.component = component
        super().__init__("; ".join(problems))


class Runs:
    """Starts, supervises, holds and cancels the cell's one running operation."""

    def __init__(
        self,
        *,
        settings: Settings,
        devices: CellDevices,
        operations: dict[str, Operation],
        stores: CellStores,
        ctx: MachineContext,
        bus: Bus,
        recorder: Recorder,
        alerts: Alerts,
        clock: Clock,
        post_outcome: PostOutcome,
    ) -> None:
        self.settings = settings
        self.devices = devices
        self.operations = operations
        self.stores = stores
        self.ctx = ctx
        self.bus = bus
        self.recorder = recorder
        self.alerts = alerts
        self.clock = clock
        self._post_outcome = post_outcome  # hands the run's outcome to the worker's queue
        self.trajectory: dict[str, Any] | None = None  # the plan of the current or last run
        self.frames = LatestFrame()  # the last frame an operation measured on, for the HMI
        self._task: asyncio.Task[None] | None = None
        self._ended: asyncio.Future[None] | None = None  # set as the run's task ends
        self._gate: PauseGate | None = None
        self._leash: Leash | None = None  # the running operation's hold on the devices
        # Called with (kind, outcome, seconds) when an operation ends, e.g. by metrics.
        self.listeners: list[Callable[[RunEnded], None]] = []
        # Called with the operation's name as a run starts, before its first step.
        self.start_listeners: list[Callable[[str], None]] = []

    def is_current(self, run_id: str) -> bool:
        running = self.ctx.operation
        return running is not None and running.run_id == run_id

    # --- start -------------------------------------------------------------

    def start(self, name: str, run_id: str, params: dict[str, Any]) -> None:
        """Start operation `name` as run `run_id` with the request's parameters."""
        for listener in self.start_listeners:
            listener(name)
        self._gate = PauseGate(self.clock)
        running = RunningOperation(name, run_id, self.clock.time(), dict(params))
        self.ctx.operation = running
        self.ctx.operation_data = dict(params)
        self.ctx.operation_result = None
        self.recorder.run_started(running)
        if name == "trajectory":
            # The last run's plan goes now, not when this one is planned: from the 202 on,
            # GET /trajectory is this run's (not planned yet), never the last one as running.
            self.trajectory = {
                "run_id": run_id,
                "planned": False,
                "planned_path": [],
                "workpieces": [],
            }
        self._leash = Leash(run_id, self.devices.glue)
        robot, glue = leashed(self.devices.robot, self.devices.glue, self._leash)
        op_ctx = OperationContext(
            robot=robot,
            glue=glue,
            camera=self.devices.camera,
            settings=self.settings,
            stores=self.stores,
            params=dict(params),
            listener=_RunListener(self, run_id),
            gate=self._gate,
            run_id=run_id,
            operation=name,
            frames=self.frames,
            clock=self.clock,
        )
        operation = _from_safe_position(self.operations[name])
        self._ended = ended = asyncio.get_running_loop().create_future()
        self._task = asyncio.create_task(
            self._supervise(operation, op_ctx, ended), name=f"operation-{name}"
        )
        # A task cancelled before its first step never runs _supervise's `finally`.
        self._task.add_done_callback(lambda _: None if ended.done() else ended.set_result(None))

    async def _supervise(
        self, operation: Operation, op_ctx: OperationContext, ended: asyncio.Future[None]
    ) -> None:
        """Run one operation and post its outcome; `ended` is set as it ends, however.

        Why `ended`: set in the task's last step, it wakes a cancel waiting for the
        run a loop turn sooner than the task's own done callbacks would.
        """
        try:
            await self._supervised(operation, op_ctx)
        finally:
            if not ended.done():
                ended.set_result(None)

    async def _supervised(self, operation: Operation, op_ctx: OperationContext) -> None:
        """Run one operation (budget and retries in supervision.py); post its outcome."""
        run_id = op_ctx.run_id

        def on_retry(attempt: int, code: str, succeeded: bool) -> None:
            self.recorder.recovery(run_id, code, attempt, succeeded)
            running = self.ctx.operation
            self.bus.publish(
                "progress",
                {
                    "operation": running.name if running else "",
                    "run_id": run_id,
                    "recovery_attempt": attempt,
                    "recovered": succeeded,
                    "cause": code,
                },
            )

        outcome: RunOutcome = await supervise(operation, op_ctx, self.settings, on_retry)
        if outcome.result is not None:
            self._post_outcome(
                Event.OPERATION_COMPLETED, RunCompletedPayload(run_id, outcome.result)
            )
        else:
            failure = RunFailedPayload(
                run_id, outcome.code, outcome.message, outcome.component, outcome.trace
            )
            self._post_outcome(Event.OPERATION_FAILED, failure)

    # --- while it runs -------------------------------------------------------

    def on_plan(self, run_id: str, plan: PlannedPath) -> None:
        if self.is_current(run_id):
            self.trajectory = {
                "run_id": run_id,
                "planned": True,
                "planned_path": plan.waypoints,
                "workpieces": plan.workpieces,
            }
            self.recorder.planned(run_id, len(plan.workpieces))

    def on_progress(self, run_id: str, progress: dict[str, Any]) -> None:
        running = self.ctx.operation
        if running is None or running.run_id != run_id:
            return
        running.progress.update(progress)
        self.recorder.progress(run_id, running.progress)
        self.bus.publish(
            "progress",
            {
                "operation": running.name,
                "run_id": run_id,
                "state": self.ctx.state.value,
                **running.progress,
            },
        )

    async def hold_now(self) -> None:
        """Pause: valve closed and robot stopped at once, as a halt, and the run held.

        Why the devices are commanded here rather than left to the run: the
        commands leave at once, whatever the run is awaiting; the gate closes as
        soon as both are on their way, before their answers (`safe_halt`'s `then`).
        The run, told by its gate, then stops its own move, closes the valve
        again (an open it had queued may land after this close) and holds;
        PAUSED is entered only once both devices answered and the run holds.
        Raises PauseNotHeld when either is not confirmed.
        """
        report = await self.devices.safe_halt(self.settings.emergency_stop_timeout, self.hold)
        if report.errors:
            component = report.errors[0].split(":", 1)[0]
            raise PauseNotHeld("glue" if component.startswith("glue") else "robot", report.errors)
        limit = self.settings.pause_hold_timeout
        if not await self.settled(limit):
            problem = f"the run did not hold within {limit:g} s (pause_hold_timeout)"
            raise PauseNotHeld("operation", [problem])

    def hold(self) -> None:
        """Close the gate: the operation stops where it is (a move under way is
        interrupted) and holds until the gate opens."""
        if self._gate is not None:
            self._gate.pause()

    async def settled(self, timeout: float) -> bool:
        """Wait (at most `timeout` s) until the run holds: no step of it in progress, or
        its task ended. False when it did not in time."""
        gate, task = self._gate, self._task
        if gate is None or not gate.in_step or task is None or task.done():
            return True  # nothing in progress: settled without a task
        waiter = asyncio.ensure_future(gate.settled())
        try:
            done, _ = await asyncio.wait(
                {waiter, task}, timeout=timeout, return_when=asyncio.FIRST_COMPLETED
            )
        finally:
            waiter.cancel()
        return bool(done)

    def release(self) -> None:
        """Open the gate: a held operation continues."""
        if self._gate is not None:
            self._gate.resume()

    # --- end -----------------------------------------------------------------

    def record_end(self, event: Event, payload: Payload) -> None:
        """The run's outcome on record and its listeners told, before it is cancelled."""
        running = self.ctx.operation
        if running is None:
            return
        outcome = RUN_OUTCOME.get(event, "failed")
        took = self.clock.time() - running.started_at
        result = payload.result if isinstance(payload, RunCompletedPayload) else None
        if result is not None:
            paused = self._gate.paused_seconds() if self._gate is not None else 0.0
            self.alerts.of_completed_run(running.name, took - paused, result.warnings)
        error = None
        if outcome == "failed":
            error = payload.message if isinstance(payload, RunFailedPayload) else event.value
        parts = 0
        plan = self.trajectory
        if running.name == "trajectory" and plan is not None and plan["run_id"] == running.run_id:
            parts = len(plan["workpieces"])
        data = result.as_dict() if result else None
        inspection = result.inspection if result is not None and outcome == "completed" else None
        self.recorder.run_ended(running.run_id, outcome, data, error, parts, inspection)
        ended = RunEnded(
            running.run_id,
            running.name,
            outcome,
            took,
            self.ctx.state.value,
            data,
            error,
            parts,
            dict(running.params),
        )
        for listener in self.listeners:
            listener(ended)

    def cut_leash(self, *, halt_follows: bool = True) -> None:
        """From now on the running operation commands no move and no glue.

        An e-stop cuts it as it arrives, and every other halt before it is made,
        so nothing the run sends after the halt can undo it (an opening it has
        waiting for the dispenser's line included); the cancellation follows in
        the worker. `halt_follows`: the halt made next reports to `halted`.
        """
        if self._leash is not None:
            self._leash.cut_now(halt_follows=halt_follows)

    def halted(self, valve_closed: bool) -> None:
        """The halt after the cut has ended (`valve_closed`: the valve read back closed)."""
        if self._leash is not None:
            self._leash.halted(valve_closed)

    async def cancel(self) -> None:
        """Cancel the running operation and wait (bounded) until it has stopped."""
        task, self._task = self._task, None
        ended, self._ended = self._ended, None
        self.cut_leash(halt_follows=False)  # it moves nothing, whatever becomes of the cancel
        if self._gate is not None:
            self._gate.resume()  # a held operation must see the cancellation, not the gate
        self._gate = None
        self.ctx.operation = None
        if task is not None and not task.done() and ended is not None:
            task.cancel()
            try:
                # Not asyncio.wait_for (loses a cancel on 3.11). On time out, or if the
                # worker is cancelled meanwhile, it is `ended` that is cancelled, never
                # the run a second time: its own stop sequence is left to finish.
                async with asyncio.timeout(self.settings.emergency_stop_timeout):
                    await ended
            except TimeoutError:
                pass  # the leash is cut: whatever it still does, it moves nothing

    async def stop(self) -> None:
        """At shutdown: the task goes, whatever it was doing."""
        self.cut_leash(halt_follows=False)
        self.halted(False)  # a halt the run's close would wait for may never report
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)


def _from_safe_position(operation: Operation) -> Operation:
    """`operation`, preceded by the move to the safe position: a run's first step.

    Why: the cell never moves the robot by itself (not on entering IDLE, not
    on a reset); the run a person commanded starts from a known pose.
    """

    async def run(ctx: OperationContext) -> OperationResult:
        await move_to_safe_position(ctx)
        return as_result(await operation(ctx))

    return run


class _RunListener:
    """What one run's context reports to; a run that has ended is no longer heard."""

    def __init__(self, runs: Runs, run_id: str) -> None:
        self._runs = runs
        self._run_id = run_id

    def on_progress(self, progress: dict[str, Any]) -> None:
        self._runs.on_progress(self._run_id, progress)

    def on_plan(self, plan: PlannedPath) -> None:
        self._runs.on_plan(self._run_id, plan)
