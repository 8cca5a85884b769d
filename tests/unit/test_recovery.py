"""Automatic recovery retries recoverable faults in place, then stops in ERROR;
critical faults are never retried; a cell held in ERROR raises an alert."""

from __future__ import annotations

import asyncio
from typing import Any

from server.common.errors import OperationError
from server.core.machine.transitions import Event, State
from server.core.operations import OperationContext, OperationResult, OperationWarning
from tests.conftest import START_PAYLOAD, wait_for_state
from tests.fakes import FakeClock


def failing(code: str, calls: list[int], *, succeed_on: int | None = None):
    async def operation(ctx: OperationContext) -> dict[str, Any]:
        calls.append(len(calls) + 1)
        if succeed_on is not None and len(calls) >= succeed_on:
            return {"found": True}
        raise OperationError(code, f"{code.lower()} (attempt {len(calls)})")

    return operation


def recovering(fast_settings, **overrides):
    return fast_settings.model_copy(
        update={
            "auto_recovery_enabled": True,
            "error_recovery_attempts": 2,
            "error_recovery_delay": 0.01,
            **overrides,
        }
    )


async def test_a_recoverable_fault_is_retried_then_stays_in_error(make_worker, fast_settings):
    calls: list[int] = []
    worker = await make_worker(
        recovering(fast_settings),
        operations={"calibrate_robot": failing("MARKER_NOT_FOUND", calls)},
    )
    await worker.request(Event.CALIBRATE_ROBOT_REQUESTED, source="test")
    await wait_for_state(worker, State.ERROR)
    assert calls == [1, 2, 3]  # the first try and two retries
    assert worker.ctx.error.classification == "recoverable"
    await asyncio.sleep(0.1)
    assert worker.ctx.state is State.ERROR  # never leaves ERROR by itself


async def test_a_recovery_that_succeeds_completes_the_operation(make_worker, fast_settings):
    calls: list[int] = []
    op = failing("MARKER_NOT_FOUND", calls, succeed_on=2)
    worker = await make_worker(recovering(fast_settings), operations={"calibrate_robot": op})
    await worker.request(Event.CALIBRATE_ROBOT_REQUESTED, source="test")
    await wait_for_state(worker, State.IDLE)
    assert calls == [1, 2]
    assert worker.ctx.operation_result == {"found": True}


async def test_a_critical_fault_is_never_retried(make_worker, fast_settings) -> None:
    calls: list[int] = []
    worker = await make_worker(
        recovering(fast_settings), operations={"trajectory": failing("WORKSPACE_VIOLATION", calls)}
    )
    await worker.request(Event.START_REQUESTED, source="test", payload=START_PAYLOAD)
    await wait_for_state(worker, State.ERROR)
    assert calls == [1]
    assert worker.ctx.error.classification == "critical"


async def test_without_auto_recovery_nothing_is_retried(make_worker, fast_settings) -> None:
    calls: list[int] = []
    worker = await make_worker(operations={"calibrate_robot": failing("MARKER_NOT_FOUND", calls)})
    await worker.request(Event.CALIBRATE_ROBOT_REQUESTED, source="test")
    await wait_for_state(worker, State.ERROR)
    assert calls == [1]


async def test_a_cell_left_in_error_raises_an_alert(make_worker, fast_settings) -> None:
    clock = FakeClock()
    settings = fast_settings.model_copy(update={"error_state_timeout": 300})
    worker = await make_worker(settings, clock=clock)
    alerts = worker.bus.subscribe(16, types=["alert"])
    await worker.stops.stop(source="test")
    await clock.advance(299)
    assert alerts.pending == 0
    await clock.advance(1)
    message = await asyncio.wait_for(alerts.get(), 5)
    assert message.data["code"] == "ERROR_STATE_TIMEOUT"
    assert "emergency stop" in message.data["message"]


async def test_leaving_error_in_time_raises_no_alert(make_worker, fast_settings) -> None:
    clock = FakeClock()
    settings = fast_settings.model_copy(update={"error_state_timeout": 300})
    worker = await make_worker(settings, clock=clock)
    alerts = worker.bus.subscribe(16, types=["alert"])
    await worker.stops.stop(source="test")
    await worker.request(Event.RESET_REQUESTED, source="test")
    await clock.advance(600)
    assert alerts.pending == 0


async def test_a_run_close_to_its_budget_is_warned_of_and_the_cell_runs_on(
    make_worker, fast_settings
) -> None:
    async def slow(ctx: OperationContext) -> dict[str, Any]:
        await ctx.clock.sleep(170)  # 85 % of the budget below; warned of above 80 %
        return {}

    clock = FakeClock()
    worker = await make_worker(
        fast_settings.model_copy(update={"processing_timeout": 200}),
        operations={"calibrate_robot": slow},
        clock=clock,
    )
    alerts = worker.bus.subscribe(16, types=["alert"])
    await worker.request(Event.CALIBRATE_ROBOT_REQUESTED, source="test")
    await clock.advance(170)
    message = await asyncio.wait_for(alerts.get(), 5)
    assert message.data["code"] == "SLOW_OPERATION"
    assert message.data["classification"] == "warning"
    assert "calibrate_robot took" in message.data["message"]
    await wait_for_state(worker, State.IDLE)
    assert worker.ctx.stop_reason is None  # a warning never stops the cell


async def test_an_operation_can_report_warnings_with_its_result(make_worker) -> None:
    async def degrading(ctx: OperationContext) -> OperationResult:
        return OperationResult({}, (OperationWarning("CALIBRATION_DEGRADING", "creeping up"),))

    worker = await make_worker(operations={"calibrate_robot": degrading})
    alerts = worker.bus.subscribe(16, types=["alert"])
    await worker.request(Event.CALIBRATE_ROBOT_REQUESTED, source="test")
    message = await asyncio.wait_for(alerts.get(), 5)
    assert message.data["code"] == "CALIBRATION_DEGRADING"
    assert message.data["component"] == "calibrate_robot"
    await wait_for_state(worker, State.IDLE)


async def test_a_quick_run_raises_no_warning(make_worker) -> None:
    async def quick(ctx: OperationContext) -> dict[str, Any]:
        return {"mean_error_mm": 0.01}

    worker = await make_worker(operations={"calibrate_robot": quick})
    alerts = worker.bus.subscribe(16, types=["alert"])
    await worker.request(Event.CALIBRATE_ROBOT_REQUESTED, source="test")
    await wait_for_state(worker, State.IDLE)
    await asyncio.sleep(0.05)
    assert alerts.pending == 0
