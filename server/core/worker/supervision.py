"""Running one operation: its time budget, its retries, and what its outcome means.

`processing_timeout` bounds the operation's running time, not counting time
held in PAUSED. A failure classified *recoverable* (a marker not seen, no part
found) is retried in place, while the cell is still in the operational state,
when auto_recovery_enabled: after error_recovery_delay × attempt seconds, up to
error_recovery_attempts times, each attempt reported. The cell never leaves
ERROR by itself: once the retries are spent the failure goes to the machine
like any other, and only a person's reset clears it.
"""

from __future__ import annotations

import asyncio
import logging
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from server.common.errors import DeviceError, OperationError
from server.core.infra.clock import Timer
from server.core.machine.faults import classify
from server.core.operations.base import Operation, OperationContext, OperationResult
from server.settings.model import Settings

log = logging.getLogger(__name__)

RetryReporter = Callable[[int, str, bool], None]  # attempt, error code, succeeded


@dataclass(frozen=True)
class RunOutcome:
    """How an operation ended: its result, or the fault that ended it."""

    result: OperationResult | None = None
    code: str = ""
    message: str = ""
    component: str = "operation"
    attempts: int = 1
    trace: str = ""  # the stack of the exception that ended the run, for the fault's record

    @property
    def succeeded(self) -> bool:
        return self.result is not None


class OperationTimeout(Exception):
    """The operation ran past processing_timeout."""


async def _run_once(operation: Operation, op_ctx: OperationContext, budget: float) -> Any:
    """Run `operation` in this task, cancelled once it has run `budget` s (held time not
    counted): OperationTimeout then.

    Why in this task, under asyncio.timeout and a timer: a task for the operation and
    one sleeping for its budget cost every run two tasks and a wait on both, for a
    limit that almost never fires. asyncio.timeout cancels this very task and tells
    its own expiry from a cancel from outside, which it passes on (a cancel is never
    lost, unlike with asyncio.wait_for on 3.11).
    """
    limit = _Budget(op_ctx, budget)
    try:
        async with limit:
            return await operation(op_ctx)
    except Exception as exc:
        if limit.expired:  # whatever the operation made of the cancellation
            raise OperationTimeout(f"operation exceeded processing_timeout ({budget:g} s)") from exc
        raise


class _Budget:
    """Cancels the task it is entered in once the run has used `budget` s, time held
    paused not counted (the block then raises TimeoutError and `expired` is set).

    It looks again when the budget would run out, and every 0.05 s at least while
    the run is held (the paused time keeps moving the end). The asyncio.timeout it
    uses is dropped on leaving: it refers to the task, and a run's frames kept by
    its cancellation's traceback would otherwise hold the task in a reference
    cycle, left for the garbage collector after every cancelled run.
    """

    def __init__(self, op_ctx: OperationContext, budget: float) -> None:
        self._clock = op_ctx.clock
        self._gate = op_ctx.gate
        self._budget = budget
        self._started = self._clock.monotonic()
        self._deadline: asyncio.Timeout | None = None
        self._timer: Timer | None = None
        self.expired = False

    async def __aenter__(self) -> None:
        self._deadline = asyncio.timeout(None)
        await self._deadline.__aenter__()
        self._look()

    async def __aexit__(self, *exc_info: Any) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        deadline, self._deadline = self._deadline, None
        assert deadline is not None
        try:
            await deadline.__aexit__(*exc_info)  # raises TimeoutError once expired
        finally:
            self.expired = deadline.expired()

    def _look(self) -> None:
        deadline = self._deadline
        if deadline is None:
            return
        used = self._clock.monotonic() - self._started - self._gate.paused_seconds()
        remaining = self._budget - used
        if remaining <= 0 and not self._gate.paused:
            self._timer = None
            deadline.reschedule(asyncio.get_running_loop().time())  # expires now
            return
        self._timer = self._clock.call_later(max(remaining, 0.05), self._look)


async def supervise(
    operation: Operation, op_ctx: OperationContext, settings: Settings, on_retry: RetryReporter
) -> RunOutcome:
    """Run `operation` to its end under the budget and the retry policy.

    `on_retry(n, code, succeeded)` is called when retry n has run: every
    recovery attempt is on record, with the fault code that caused it.
    """
    attempt, cause = 1, ""
    while True:
        outcome = await _attempt(operation, op_ctx, settings, attempt)
        if attempt > 1:
            on_retry(attempt - 1, cause, outcome.succeeded)
        retry = (
            not outcome.succeeded
            and settings.auto_recovery_enabled
            and classify(outcome.code) == "recoverable"
            and attempt <= settings.error_recovery_attempts
        )
        if not retry:
            return outcome
        delay = settings.error_recovery_delay * attempt
        log.warning("%s (attempt %d); retrying in %.1f s", outcome.message, attempt, delay)
        await op_ctx.clock.sleep(delay)
        attempt, cause = attempt + 1, outcome.code


async def _attempt(
    operation: Operation, op_ctx: OperationContext, settings: Settings, attempt: int
) -> RunOutcome:
    try:
        result = await _run_once(operation, op_ctx, settings.processing_timeout)
    except OperationTimeout as exc:
        return RunOutcome(code="OPERATION_TIMEOUT", message=str(exc), attempts=attempt)
    except OperationError as exc:
        return RunOutcome(code=exc.code, message=str(exc), attempts=attempt, trace=stack_of(exc))
    except DeviceError as exc:
        return RunOutcome(
            code="DEVICE_FAULT",
            message=str(exc),
            component=exc.device,
            attempts=attempt,
            trace=stack_of(exc),
        )
    except asyncio.CancelledError:
        raise
    except Exception as exc:
        message = f"{type(exc).__name__}: {exc}"
        return RunOutcome(code="INTERNAL", message=message, attempts=attempt, trace=stack_of(exc))
    return RunOutcome(result=as_result(result), attempts=attempt)


# A fault row keeps at most this much of a stack, its innermost end: where it failed.
STACK_LIMIT = 8_000


def stack_of(exc: BaseException) -> str:
    """The exception's traceback as text (with its causes), cut to STACK_LIMIT characters.

    Kept with the fault (journal, log line, GET /errors/{seq}) so a technician can
    tell a driver's refusal from a crash in the cell's own code without a debugger.
    """
    text = "".join(traceback.format_exception(exc)).rstrip()
    return text if len(text) <= STACK_LIMIT else "...\n" + text[-STACK_LIMIT:]


def as_result(value: Any) -> OperationResult:
    """An operation's return as an OperationResult.

    Why accept more: an integrator's operation (or `blocking_operation` around
    a legacy method) may return a plain dict or value; it is kept as the data.
    """
    if isinstance(value, OperationResult):
        return value
    return OperationResult(value if isinstance(value, dict) else {"value": value})
