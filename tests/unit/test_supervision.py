"""Supervision of one operation run (server/core/worker/supervision.py), without the worker.

The budget (processing_timeout) counts running time only, not time held in PAUSED;
recoverable failures are retried in place when auto_recovery_enabled, up to
error_recovery_attempts, each retry reported with its cause; a DeviceError becomes
DEVICE_FAULT with the device as component, anything unexpected INTERNAL.

Small budgets and delays keep every test well under a second of real time.
`ok()`, `data_of()` and `run()` are the only places that know what an operation returns
and how supervise is called: change them when operations return OperationResult and
supervise takes a clock.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

import pytest

from server.common.errors import DeviceError, DeviceTimeout, OperationError
from server.core.operations.base import Operation, OperationContext, OperationResult
from server.core.worker.supervision import STACK_LIMIT, RunOutcome, stack_of, supervise
from server.settings.model import Settings
from tests.fakes import FakeCamera, FakeGlue, FakeRobot

Retry = tuple[int, str, bool]


def settings(**overrides: Any) -> Settings:
    values: dict[str, Any] = {
        "processing_timeout": 0.3,
        "auto_recovery_enabled": True,
        "error_recovery_attempts": 2,
        "error_recovery_delay": 0.01,
    }
    values.update(overrides)
    return Settings(**values)


def context(config: Settings) -> OperationContext:
    return OperationContext(
        robot=FakeRobot(),
        glue=FakeGlue(),
        camera=FakeCamera(),
        settings=config,
        stores=None,  # type: ignore[arg-type]  # no operation here touches the stores
        params={},
        run_id="run-1",
        operation="test",
    )


def ok(data: dict[str, Any]) -> OperationResult:
    """What an operation returns on success."""
    return OperationResult(data)


def data_of(outcome: RunOutcome) -> dict[str, Any] | None:
    """The successful operation's data as the outcome carries it."""
    return outcome.result.data if outcome.result is not None else None


async def run(
    operation: Operation, config: Settings, ctx: OperationContext | None = None
) -> tuple[RunOutcome, list[Retry]]:
    retries: list[Retry] = []

    def on_retry(attempt: int, code: str, succeeded: bool) -> None:
        retries.append((attempt, code, succeeded))

    outcome = await supervise(operation, ctx or context(config), config, on_retry)
    return outcome, retries


def failing(*codes: str, then: dict[str, Any] | None = None) -> tuple[Operation, list[float]]:
    """Fails with codes[0], codes[1], ... in turn; then succeeds with `then` (if given)."""
    calls: list[float] = []

    async def operation(ctx: OperationContext) -> Any:
        calls.append(time.monotonic())
        if len(calls) <= len(codes) or then is None:
            code = codes[min(len(calls), len(codes)) - 1]
            raise OperationError(code, f"{code} on attempt {len(calls)}")
        return ok(then)

    return operation, calls


# --- success and the budget ------------------------------------------------------------------


async def test_a_successful_run_hands_back_its_result_once() -> None:
    calls: list[int] = []

    async def operation(ctx: OperationContext) -> Any:
        calls.append(1)
        return ok({"waypoints": 7})

    outcome, retries = await run(operation, settings())
    assert outcome.succeeded and data_of(outcome) == {"waypoints": 7}
    assert (outcome.code, outcome.attempts) == ("", 1)
    assert calls == [1] and retries == []


async def test_a_run_past_its_budget_is_cancelled_and_times_out() -> None:
    cancelled = asyncio.Event()

    async def operation(ctx: OperationContext) -> Any:
        try:
            await asyncio.sleep(10)
        except asyncio.CancelledError:
            cancelled.set()
            raise
        return ok({})

    started = time.monotonic()
    outcome, retries = await run(operation, settings(processing_timeout=0.2))
    took = time.monotonic() - started
    assert not outcome.succeeded and data_of(outcome) is None
    assert outcome.code == "OPERATION_TIMEOUT"
    assert "processing_timeout (0.2 s)" in outcome.message
    assert cancelled.is_set(), "the operation itself must be cancelled, not left running"
    assert 0.2 <= took < 1.0
    assert retries == [], "a timeout is critical: never retried"


async def pause_while_running(ctx: OperationContext, after: float, hold: float) -> None:
    await asyncio.sleep(after)
    ctx.gate.pause()
    await asyncio.sleep(hold)
    ctx.gate.resume()


async def test_time_held_in_pause_does_not_count_against_the_budget() -> None:
    config = settings(processing_timeout=0.3)
    ctx = context(config)

    async def operation(ctx: OperationContext) -> Any:
        for _ in range(10):  # 0.1 s of work with a safe point every 10 ms
            await ctx.gate.checkpoint()
            await asyncio.sleep(0.01)
        return ok({"done": True})

    started = time.monotonic()
    pauser = asyncio.create_task(pause_while_running(ctx, after=0.03, hold=0.5))
    outcome, _ = await run(operation, config, ctx)
    await pauser
    assert time.monotonic() - started > config.processing_timeout  # longer than the budget
    assert outcome.succeeded and data_of(outcome) == {"done": True}


async def test_running_time_before_and_after_a_pause_adds_up() -> None:
    config = settings(processing_timeout=0.2)
    ctx = context(config)

    async def operation(ctx: OperationContext) -> Any:
        for _ in range(30):  # 0.3 s of work in all: over the budget, pause or not
            await ctx.gate.checkpoint()
            await asyncio.sleep(0.01)
        return ok({})

    pauser = asyncio.create_task(pause_while_running(ctx, after=0.1, hold=0.2))
    outcome, _ = await run(operation, config, ctx)
    await pauser
    assert outcome.code == "OPERATION_TIMEOUT"


# --- retries ---------------------------------------------------------------------------------


async def test_a_recoverable_failure_is_retried_up_to_the_limit_each_retry_reported() -> None:
    operation, calls = failing("MARKER_NOT_FOUND")
    outcome, retries = await run(operation, settings(error_recovery_attempts=2))
    assert len(calls) == 3  # the first attempt and two retries
    assert outcome.code == "MARKER_NOT_FOUND" and outcome.attempts == 3
    assert "attempt 3" in outcome.message  # the last failure is the one reported
    assert retries == [(1, "MARKER_NOT_FOUND", False), (2, "MARKER_NOT_FOUND", False)]


async def test_a_retry_that_succeeds_completes_the_run() -> None:
    operation, calls = failing("WORKPIECE_NOT_FOUND", then={"found": 1})
    outcome, retries = await run(operation, settings())
    assert outcome.succeeded and data_of(outcome) == {"found": 1}
    assert len(calls) == 2 and outcome.attempts == 2
    assert retries == [(1, "WORKPIECE_NOT_FOUND", True)]


async def test_each_retry_is_reported_with_the_failure_that_caused_it() -> None:
    operation, _ = failing("MARKER_NOT_FOUND", "VISION_TIMEOUT", then={})
    outcome, retries = await run(operation, settings(error_recovery_attempts=3))
    assert outcome.succeeded
    assert retries == [(1, "MARKER_NOT_FOUND", False), (2, "VISION_TIMEOUT", True)]


async def test_retries_wait_longer_each_time() -> None:
    operation, calls = failing("MARKER_NOT_FOUND")
    await run(operation, settings(error_recovery_delay=0.05, error_recovery_attempts=2))
    first_gap, second_gap = calls[1] - calls[0], calls[2] - calls[1]
    assert first_gap >= 0.05 * 0.95  # error_recovery_delay × 1
    assert second_gap >= 0.10 * 0.95  # error_recovery_delay × 2


@pytest.mark.parametrize(
    "overrides",
    [{"auto_recovery_enabled": False}, {"error_recovery_attempts": 0}],
    ids=["auto-recovery-off", "no-attempts"],
)
async def test_without_auto_recovery_nothing_is_retried(overrides: dict[str, Any]) -> None:
    operation, calls = failing("MARKER_NOT_FOUND", then={})
    outcome, retries = await run(operation, settings(**overrides))
    assert len(calls) == 1 and retries == []
    assert outcome.code == "MARKER_NOT_FOUND" and outcome.attempts == 1


@pytest.mark.parametrize("code", ["WORKSPACE_VIOLATION", "PATH_EMPTY", "SOMETHING_NEW"])
async def test_a_critical_failure_is_never_retried(code: str) -> None:
    operation, calls = failing(code, then={})
    outcome, retries = await run(operation, settings())
    assert len(calls) == 1 and retries == []
    assert (outcome.code, outcome.component, outcome.attempts) == (code, "operation", 1)


async def test_the_code_decides_a_retry_not_the_errors_recoverable_flag() -> None:
    calls: list[int] = []

    async def operation(ctx: OperationContext) -> Any:
        calls.append(1)
        raise OperationError("WORKSPACE_VIOLATION", "outside", recoverable=True)

    outcome, retries = await run(operation, settings())
    assert len(calls) == 1 and retries == [] and outcome.code == "WORKSPACE_VIOLATION"


# --- what a failure means --------------------------------------------------------------------


@pytest.mark.parametrize("error", [DeviceError("glue", "valve stuck"), DeviceTimeout("robot", "x")])
async def test_a_device_error_is_a_device_fault_of_that_device(error: DeviceError) -> None:
    calls: list[int] = []

    async def operation(ctx: OperationContext) -> Any:
        calls.append(1)
        raise error

    outcome, retries = await run(operation, settings())
    assert not outcome.succeeded
    assert outcome.code == "DEVICE_FAULT"
    assert outcome.component == error.device
    assert outcome.message == str(error)
    assert len(calls) == 1 and retries == []


async def test_an_unexpected_exception_is_internal() -> None:
    async def operation(ctx: OperationContext) -> Any:
        return {"ratio": 1 / 0}

    outcome, retries = await run(operation, settings())
    assert outcome.code == "INTERNAL" and outcome.component == "operation"
    assert outcome.message.startswith("ZeroDivisionError: ")
    assert retries == []
    # the stack goes with the fault (journal row, log line, GET /errors/{seq})
    assert outcome.trace.startswith("Traceback (most recent call last):")
    assert 'return {"ratio": 1 / 0}' in outcome.trace
    assert outcome.trace.endswith("ZeroDivisionError: division by zero")


def test_a_long_stack_keeps_its_innermost_end() -> None:
    try:
        raise RuntimeError("x" * (2 * STACK_LIMIT) + " the end")
    except RuntimeError as exc:
        trace = stack_of(exc)
    assert len(trace) <= STACK_LIMIT + 4
    assert trace.startswith("...\n") and trace.endswith(" the end")


async def test_cancelling_the_supervision_cancels_the_operation() -> None:
    running, cancelled = asyncio.Event(), asyncio.Event()

    async def operation(ctx: OperationContext) -> Any:
        running.set()
        try:
            await asyncio.sleep(10)
        except asyncio.CancelledError:
            cancelled.set()
            raise
        return ok({})

    task = asyncio.create_task(run(operation, settings()))
    await running.wait()
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    assert cancelled.is_set()
