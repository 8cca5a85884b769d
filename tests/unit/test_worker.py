"""The worker on in-process fakes: ordering, overflow, e-stop, operations."""

from __future__ import annotations

import asyncio
import contextlib
from typing import Any

import pytest

from server.common.errors import EventQueueFull, OperationError
from server.core.machine.events import FaultPayload, RunCompletedPayload, StopPayload
from server.core.machine.transitions import Command, Event, State
from server.core.operations import OperationContext
from server.core.worker import stop as stop_service
from server.core.worker.event_queue import Priority
from server.drivers.base import Pose
from tests.conftest import START_PAYLOAD, wait_for_state
from tests.fakes import FakeClock, FakeGlue, FakeRobot


def blocking_operation(started: asyncio.Event, cancelled: asyncio.Event):
    async def operation(ctx: OperationContext) -> dict[str, Any]:
        started.set()
        try:
            await asyncio.sleep(3600)
        except asyncio.CancelledError:
            cancelled.set()
            raise
        return {}

    return operation


async def test_comes_up_through_initializing_once_every_device_is_ready(make_worker) -> None:
    worker = await make_worker()
    events = [r.event for r in worker.ctx.history]
    assert events == ["SYSTEM_READY"]
    assert worker.ctx.previous_state is State.INITIALIZING


async def test_a_device_that_does_not_come_up_sends_the_cell_to_error(make_worker) -> None:
    robot = FakeRobot()
    robot.failing = True
    worker = await make_worker(robot=robot, wait_idle=False)
    await wait_for_state(worker, State.ERROR)
    assert worker.ctx.error.component == "robot"
    assert "robot did not come up" in worker.ctx.error.message


async def test_events_are_handled_one_at_a_time_in_arrival_order(make_worker) -> None:
    worker = await make_worker(
        operations={"calibrate_robot": blocking_operation(asyncio.Event(), asyncio.Event())}
    )
    sequence = [
        Event.CALIBRATE_ROBOT_REQUESTED,
        Event.START_REQUESTED,
        Event.CANCEL_REQUESTED,
        Event.START_REQUESTED,
        Event.PAUSE_REQUESTED,
        Event.RESUME_REQUESTED,
        Event.CANCEL_REQUESTED,
    ]
    envelopes = [
        worker.submit(
            event, source="test", payload=START_PAYLOAD if event is Event.START_REQUESTED else None
        )
        for event in sequence
    ]
    outcomes = [await envelope.future for envelope in envelopes]
    assert [o.accepted for o in outcomes] == [True, False, True, True, True, True, True]
    assert [o.state for o in outcomes] == [
        State.CALIBRATING_ROBOT,
        State.CALIBRATING_ROBOT,
        State.IDLE,
        State.EXECUTING_TRAJECTORY,
        State.PAUSED,
        State.EXECUTING_TRAJECTORY,
        State.IDLE,
    ]
    assert [r.event_id for r in worker.ctx.history][-6:] == [
        o.event_id for o in outcomes if o.accepted
    ]


async def test_a_full_queue_refuses_loudly_and_drops_nothing(make_worker, fast_settings) -> None:
    worker = await make_worker(fast_settings.model_copy(update={"event_queue_size": 3}))
    worker._task.cancel()  # hold the worker so the queue can fill
    await asyncio.gather(worker._task, return_exceptions=True)
    accepted = [worker.submit(Event.PAUSE_REQUESTED, source="test") for _ in range(3)]
    with pytest.raises(EventQueueFull, match="3 events waiting"):
        worker.submit(Event.PAUSE_REQUESTED, source="test")
    assert len(worker.queue) == 3
    worker._task = asyncio.create_task(worker._run())
    outcomes = [await envelope.future for envelope in accepted]
    assert len(outcomes) == 3 and worker.stats.processed >= 3


async def test_estop_overtakes_a_full_queue(make_worker, fast_settings) -> None:
    glue, robot = FakeGlue(), FakeRobot()
    worker = await make_worker(
        fast_settings.model_copy(update={"event_queue_size": 5}), glue=glue, robot=robot
    )
    worker._task.cancel()
    await asyncio.gather(worker._task, return_exceptions=True)
    queued = [worker.submit(Event.START_REQUESTED, source="test") for _ in range(5)]
    with pytest.raises(EventQueueFull):
        worker.submit(Event.START_REQUESTED, source="test")
    estop = asyncio.create_task(worker.stops.stop(source="test"))
    await asyncio.sleep(0.05)
    # The devices were halted before the worker even ran again.
    assert robot.stops >= 1 and glue.valve_log and glue.valve_log[-1][1] is False
    worker._task = asyncio.create_task(worker._run())
    outcome = await estop
    assert outcome.accepted and outcome.state is State.ERROR
    later = [await envelope.future for envelope in queued]
    assert not any(o.accepted for o in later)  # all refused in ERROR, none lost
    assert worker.ctx.history[-1].event == "EMERGENCY_STOP"


async def test_a_begun_stop_halts_at_once_and_is_one_event_however_often_posted(
    make_worker,
) -> None:
    """`begin` commands both devices before it returns; the stop is queued once, with the
    reason of whoever posts it first (the route), even if the lane posts it again."""
    glue, robot = FakeGlue(), FakeRobot()
    worker = await make_worker(glue=glue, robot=robot)
    stops_before = robot.stops
    begun = worker.stops.begin()
    assert robot.stops == stops_before + 1 and glue.valve_log[-1][1] is False
    outcome = await begun.finish(source="route", payload=StopPayload("guard door"))
    assert begun.post(source="lane") is begun.envelope  # nothing queued again
    assert outcome.accepted and outcome.state is State.ERROR
    assert "guard door" in worker.ctx.stop_reason.message
    assert [r.event for r in worker.ctx.history].count("EMERGENCY_STOP") == 1


async def test_leaving_an_operational_state_cancels_its_operation(make_worker) -> None:
    started, cancelled = asyncio.Event(), asyncio.Event()
    glue = FakeGlue()
    worker = await make_worker(
        operations={"calibrate_camera": blocking_operation(started, cancelled)}, glue=glue
    )
    await worker.request(Event.CALIBRATE_CAMERA_REQUESTED, source="test")
    await asyncio.wait_for(started.wait(), 5)
    outcome = await worker.request(Event.CANCEL_REQUESTED, source="test")
    assert outcome.accepted and outcome.state is State.IDLE
    assert cancelled.is_set()
    assert glue.valve_open is False and worker.ctx.operation is None


async def spraying(make_worker) -> tuple[Any, FakeGlue, FakeRobot]:
    """A worker whose run has opened the valve, with its fake dispenser and robot."""
    glue, robot = FakeGlue(), FakeRobot(speed_factor=2)
    worker = await make_worker(glue=glue, robot=robot)
    await worker.request(Event.START_REQUESTED, source="test", payload=START_PAYLOAD)
    async with asyncio.timeout(10):
        while not glue.valve_open:
            await asyncio.sleep(0.002)
    return worker, glue, robot


async def test_estop_mid_run_closes_the_valve_and_stops_the_robot(make_worker) -> None:
    worker, glue, robot = await spraying(make_worker)
    outcome = await worker.stops.stop(source="test", payload=StopPayload("hand in cell"))
    assert outcome.state is State.ERROR
    assert glue.valve_open is False and not robot.moving and robot.stops >= 1
    assert worker.ctx.stop_reason.code == "EMERGENCY_STOP"
    assert "hand in cell" in worker.ctx.stop_reason.message
    assert worker.ctx.operation is None


async def test_an_estop_halts_once_on_arrival_with_its_runs_leash_cut(
    make_worker, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The stop's HALT is the halt it made on arrival, its run's leash cut first; no other.

    The same two commands again before the run's cancellation would queue behind the
    stop's own on each device's line (the answer a round trip later); an opening the
    run had waiting for the dispenser's line is refused by the leash's cut, so no halt
    after the cancellation is needed for it.
    """
    worker, glue, robot = await spraying(make_worker)
    halts: list[str] = []
    safe_halt = worker.devices.safe_halt

    async def halting(timeout: float, then: Any = None) -> Any:
        cut = worker.runs._leash is not None and worker.runs._leash.cut and glue.drops
        halts.append("leash cut, openings dropped" if cut else "leash not cut")
        return await safe_halt(timeout, then)

    worker.devices.safe_halt = halting  # type: ignore[method-assign]
    made = stop_service.halt_at_once
    on_arrival: list[bool] = []

    def at_once(devices: Any, timeout: float) -> Any:
        on_arrival.append(True)
        return made(devices, timeout)

    monkeypatch.setattr(stop_service, "halt_at_once", at_once)
    outcome = await worker.stops.stop(source="test")
    assert outcome.accepted and outcome.state is State.ERROR
    assert on_arrival == [True] and halts == ["leash cut, openings dropped"]
    assert glue.valve_open is False and not robot.moving


async def test_a_stopped_runs_own_close_needs_no_exchange_once_the_halt_closed_it(
    make_worker,
) -> None:
    """The halt's close, read back closed after the leash was cut, is the run's last.

    A close sent again as the run ends would be two more exchanges on the dispenser's
    line before the stop could answer.
    """
    worker, glue, _robot = await spraying(make_worker)
    opened_at = max(at for at, open_ in glue.valve_log if open_)
    outcome = await worker.stops.stop(source="test")
    assert outcome.state is State.ERROR
    closes = [at for at, open_ in glue.valve_log if not open_ and at > opened_at]
    assert len(closes) == 1 and glue.valve_open is False


async def test_the_runs_own_close_is_sent_when_the_halt_could_not_confirm_it(
    make_worker,
) -> None:
    worker, glue, _robot = await spraying(make_worker)
    glue.silent = True  # the halt's close gets no answer
    closes: list[bool] = []
    set_valve = glue.set_valve

    async def counting(open_: bool) -> None:
        closes.append(open_)
        await set_valve(open_)

    glue.set_valve = counting  # type: ignore[method-assign]
    outcome = await worker.stops.stop(source="test")
    assert outcome.state is State.ERROR
    assert closes == [False, False]  # the halt's, then the run's own


async def test_a_cancel_cuts_its_runs_leash_before_its_halt(make_worker) -> None:
    worker, glue, _robot = await spraying(make_worker)
    seen: list[bool] = []
    safe_halt = worker.devices.safe_halt

    async def halting(timeout: float, then: Any = None) -> Any:
        seen.append(worker.runs._leash is not None and worker.runs._leash.cut and bool(glue.drops))
        return await safe_halt(timeout, then)

    worker.devices.safe_halt = halting  # type: ignore[method-assign]
    outcome = await worker.request(Event.CANCEL_REQUESTED, source="test")
    assert outcome.accepted and outcome.state is State.IDLE
    assert seen == [True]  # one halt, the leash already cut
    assert glue.valve_open is False


async def test_pause_stops_the_run_where_it_is_and_resume_finishes_the_same_run(
    make_worker,
) -> None:
    glue, robot = FakeGlue(), FakeRobot(speed_factor=5)
    worker = await make_worker(glue=glue, robot=robot)
    started = await worker.request(Event.START_REQUESTED, source="test", payload=START_PAYLOAD)
    async with asyncio.timeout(10):
        while not worker.ctx.operation.progress.get("waypoint"):
            await asyncio.sleep(0.002)
    paused = await worker.request(Event.PAUSE_REQUESTED, source="test")
    # PAUSED is answered only once the valve is closed and the arm stands still.
    assert paused.state is State.PAUSED and glue.valve_open is False and not robot.moving
    async with asyncio.timeout(10):
        while not worker.runs._gate.holding:
            await asyncio.sleep(0.002)
    held_at = worker.ctx.operation.progress["waypoint"]
    moves_at_hold = len(robot.moves)
    await asyncio.sleep(0.2)
    assert glue.valve_open is False and len(robot.moves) == moves_at_hold
    assert worker.ctx.operation.progress["waypoint"] == held_at
    await worker.request(Event.RESUME_REQUESTED, source="test")
    await wait_for_state(worker, State.IDLE)
    assert worker.ctx.history[-1].event == "OPERATION_COMPLETED"
    result = dict(worker.ctx.operation_result or {})
    inspection = result.pop("inspection")  # the part is judged too (docs/quality.md)
    assert result == {"workpieces": ["demo"], "waypoints": 7}
    assert inspection["verdict"] in ("good", "defective")
    # One run: the robot visited each planned waypoint exactly once, in order.
    planned = [tuple(w["pose"]) for w in worker.runs.trajectory["planned_path"]]
    assert [tuple(m) for m in robot.moves if tuple(m) in planned] == planned
    assert started.event_id == worker.ctx.history[-4].event_id


async def test_a_pause_the_valve_does_not_confirm_is_refused_and_the_cell_stops(
    make_worker,
) -> None:
    glue, robot = FakeGlue(), FakeRobot(speed_factor=2)
    worker = await make_worker(glue=glue, robot=robot)
    await worker.request(Event.START_REQUESTED, source="test", payload=START_PAYLOAD)
    async with asyncio.timeout(10):
        while not glue.valve_open:
            await asyncio.sleep(0.002)
    glue.silent = True  # the close gets no answer: the hold cannot be confirmed
    refused = await worker.request(Event.PAUSE_REQUESTED, source="test")
    assert not refused.accepted and "pause not confirmed" in refused.message
    assert refused.state is State.EXECUTING_TRAJECTORY  # never reported PAUSED
    await wait_for_state(worker, State.ERROR)
    assert worker.ctx.stop_reason.component == "glue"
    assert State.PAUSED.value not in [r.new_state for r in worker.ctx.history]


async def test_a_failing_operation_ends_in_error_with_its_reason(make_worker) -> None:
    async def failing(ctx: OperationContext) -> dict[str, Any]:
        raise OperationError("MARKER_NOT_FOUND", "marker 4 not found: check lighting")

    worker = await make_worker(operations={"calibrate_robot": failing})
    await worker.request(Event.CALIBRATE_ROBOT_REQUESTED, source="test")
    await wait_for_state(worker, State.ERROR)
    assert worker.ctx.error.code == "MARKER_NOT_FOUND"
    assert worker.ctx.error.message == "marker 4 not found: check lighting"


async def test_paused_time_does_not_count_against_processing_timeout(make_worker, fast_settings):
    clock = FakeClock()
    finish = asyncio.Event()

    async def held_run(ctx: OperationContext) -> dict[str, Any]:
        await ctx.gate.checkpoint()
        await finish.wait()
        return {}

    worker = await make_worker(
        fast_settings.model_copy(update={"processing_timeout": 1.5}),
        operations={"trajectory": held_run},
        clock=clock,
    )
    await worker.request(Event.START_REQUESTED, source="test", payload=START_PAYLOAD)
    await worker.request(Event.PAUSE_REQUESTED, source="test")
    await clock.advance(2.0)  # longer than the budget, all of it paused
    assert worker.ctx.state is State.PAUSED
    await worker.request(Event.RESUME_REQUESTED, source="test")
    await clock.advance(1.0)  # 1 s of running time: inside the budget
    assert worker.ctx.state is State.EXECUTING_TRAJECTORY
    finish.set()
    await wait_for_state(worker, State.IDLE)
    assert worker.ctx.history[-1].event == "OPERATION_COMPLETED"


async def test_a_run_past_its_budget_fails_with_operation_timeout(make_worker, fast_settings):
    clock = FakeClock()
    worker = await make_worker(
        fast_settings.model_copy(update={"processing_timeout": 1.5}),
        operations={"trajectory": blocking_operation(asyncio.Event(), asyncio.Event())},
        clock=clock,
    )
    await worker.request(Event.START_REQUESTED, source="test", payload=START_PAYLOAD)
    await clock.advance(1.4)
    assert worker.ctx.state is State.EXECUTING_TRAJECTORY
    await clock.advance(0.2)
    await wait_for_state(worker, State.ERROR)
    assert worker.ctx.error.code == "OPERATION_TIMEOUT"
    assert "processing_timeout (1.5 s)" in worker.ctx.error.message


async def test_a_completion_from_an_ended_run_is_ignored(make_worker) -> None:
    worker = await make_worker()
    envelope = worker.submit(
        Event.OPERATION_COMPLETED, source="test", payload=RunCompletedPayload("old")
    )
    outcome = await envelope.future
    assert not outcome.accepted and "already ended" in outcome.message


async def test_device_fault_mid_run_ends_in_error_and_reset_waits_for_recovery(make_worker):
    glue, robot = FakeGlue(), FakeRobot(speed_factor=2)
    worker = await make_worker(glue=glue, robot=robot)
    await worker.request(Event.START_REQUESTED, source="test", payload=START_PAYLOAD)
    async with asyncio.timeout(10):
        while not glue.valve_open:
            await asyncio.sleep(0.002)
    robot.fail("connection lost")
    await wait_for_state(worker, State.ERROR)
    assert glue.valve_open is False
    assert worker.ctx.stop_reason.component == "robot"
    refused = await worker.request(Event.RESET_REQUESTED, source="test")
    assert not refused.accepted and "robot: connection lost" in refused.message
    assert worker.ctx.state is State.ERROR
    robot.recover()
    accepted = await worker.request(Event.RESET_REQUESTED, source="test")
    assert accepted.accepted and accepted.state is State.IDLE
    assert worker.ctx.stop_reason is None


async def test_a_second_fault_keeps_the_first_out_stop_reason(make_worker) -> None:
    worker = await make_worker()
    for code in ("FIRST", "SECOND"):
        worker.submit(
            Event.ERROR_OCCURRED,
            source="test",
            priority=Priority.FAULT,
            payload=FaultPayload(code, code.lower(), "test"),
        )
    await wait_for_state(worker, State.ERROR)
    await asyncio.sleep(0.05)
    assert worker.ctx.stop_reason.code == "FIRST" and worker.ctx.error.code == "SECOND"


async def test_stop_answers_every_waiting_sender(make_worker) -> None:
    worker = await make_worker()
    worker._task.cancel()
    await asyncio.gather(worker._task, return_exceptions=True)
    waiting = worker.submit(Event.START_REQUESTED, source="test")
    await worker.stop()
    with pytest.raises(Exception, match="shutting down"):
        await waiting.future


async def test_a_run_that_ends_while_paused_completes_to_idle(make_worker) -> None:
    finish = asyncio.Event()

    async def last_segment(ctx: OperationContext) -> dict[str, Any]:
        await finish.wait()  # the pause arrives while the last move is under way
        return {"done": True}

    worker = await make_worker(operations={"trajectory": last_segment})
    await worker.request(Event.START_REQUESTED, source="test", payload=START_PAYLOAD)
    assert (await worker.request(Event.PAUSE_REQUESTED, source="test")).state is State.PAUSED
    finish.set()
    await wait_for_state(worker, State.IDLE)
    assert worker.ctx.history[-1].event == "OPERATION_COMPLETED"
    assert worker.ctx.operation_result == {"done": True}


async def test_an_estop_during_a_reset_probe_wins(make_worker) -> None:
    robot = FakeRobot()
    worker = await make_worker(robot=robot)
    await worker.stops.stop(source="test")
    robot.probe_delay = 0.3  # the reset's live probe takes a while
    reset = asyncio.create_task(worker.request(Event.RESET_REQUESTED, source="test"))
    await asyncio.sleep(0.05)
    moves_before = len(robot.moves)
    stop = await worker.stops.stop(source="test")
    outcome = await reset
    assert not outcome.accepted and "overtaken by an emergency stop" in outcome.message
    assert stop.state is State.ERROR and worker.ctx.state is State.ERROR
    await asyncio.sleep(0.1)
    assert len(robot.moves) == moves_before  # no homing move after the stop


async def probing(robot: FakeRobot, reads: int) -> None:
    """Until the reset's probe has asked the robot for its position."""
    async with asyncio.timeout(10):
        while robot.position_reads == reads:
            await asyncio.sleep(0.005)


async def test_an_estop_is_decided_while_a_reset_probe_runs(make_worker) -> None:
    robot = FakeRobot()
    worker = await make_worker(robot=robot)
    await worker.stops.stop(source="test")
    robot.probe_delay = 0.5  # the reset's live probe takes a while
    reads = robot.position_reads
    reset = asyncio.create_task(worker.request(Event.RESET_REQUESTED, source="test"))
    await probing(robot, reads)
    stop = await worker.stops.stop(source="test")
    assert stop.accepted and not reset.done()  # the stop did not wait for the probe
    outcome = await reset
    assert not outcome.accepted and "overtaken by an emergency stop" in outcome.message
    assert worker.ctx.state is State.ERROR


async def test_a_fault_during_a_reset_probe_overtakes_the_reset(make_worker) -> None:
    robot = FakeRobot()
    worker = await make_worker(robot=robot)
    await worker.stops.stop(source="test")
    robot.probe_delay = 0.3
    reads = robot.position_reads
    reset = asyncio.create_task(worker.request(Event.RESET_REQUESTED, source="test"))
    await probing(robot, reads)
    fault = worker.submit(
        Event.ERROR_OCCURRED,
        source="glue",
        priority=Priority.FAULT,
        payload=FaultPayload("ALARM", "nozzle blocked", "glue"),
        bounded=False,
    )
    assert (await fault.future).accepted and not reset.done()
    outcome = await reset
    assert not outcome.accepted and "a fault while the devices were probed" in outcome.message
    assert worker.ctx.state is State.ERROR and worker.ctx.error.code == "ALARM"


async def test_one_reset_is_probed_at_a_time(make_worker) -> None:
    robot = FakeRobot()
    worker = await make_worker(robot=robot)
    await worker.stops.stop(source="test")
    robot.probe_delay = 0.2
    reads = robot.position_reads
    first = asyncio.create_task(worker.request(Event.RESET_REQUESTED, source="test"))
    await probing(robot, reads)
    second = await worker.request(Event.RESET_REQUESTED, source="test")
    assert not second.accepted and "already probing" in second.message
    allowed, reason = worker.view.allowed(Command.RESET)
    assert not allowed and "already probing" in reason
    assert "reset" not in worker.view.snapshot()["available_commands"]
    assert (await first).accepted and worker.ctx.state is State.IDLE


async def test_the_reset_probe_is_bounded_and_begins_new_link_sessions(
    make_worker, fast_settings
) -> None:
    robot, glue = FakeRobot(), FakeGlue()
    worker = await make_worker(
        fast_settings.model_copy(update={"reset_probe_timeout": 0.05}), robot=robot, glue=glue
    )
    await worker.stops.stop(source="test")
    robot.probe_delay = 3600  # a controller that never answers the probe
    refused = await worker.request(Event.RESET_REQUESTED, source="test")
    assert not refused.accepted
    assert "robot: no answer in time (reset_probe_timeout 0.05 s)" in refused.message
    assert robot.sessions == glue.sessions == 1
    robot.probe_delay = 0.0
    assert (await worker.request(Event.RESET_REQUESTED, source="test")).accepted
    assert robot.sessions == glue.sessions == 2


async def test_stop_answers_a_reset_waiting_for_its_probe(make_worker) -> None:
    robot = FakeRobot()
    worker = await make_worker(robot=robot)
    await worker.stops.stop(source="test")
    robot.probe_delay = 3600
    reads = robot.position_reads
    reset = asyncio.create_task(worker.request(Event.RESET_REQUESTED, source="test"))
    await probing(robot, reads)
    await worker.stop()
    with pytest.raises(Exception, match="shutting down"):
        await reset


async def test_a_run_that_swallows_its_cancellation_moves_nothing_after_the_stop(
    make_worker,
) -> None:
    """A cancellation lost below a run (asyncio.wait_for on Python 3.11, a library) must
    not let the run go on commanding the devices after the cell stopped."""
    started, went_on = asyncio.Event(), asyncio.Event()
    refused: list[str] = []
    glue, robot = FakeGlue(), FakeRobot()

    async def stubborn(ctx: OperationContext) -> dict[str, Any]:
        started.set()
        with contextlib.suppress(asyncio.CancelledError):  # lost, as wait_for loses one
            await asyncio.sleep(3600)
        went_on.set()
        for command in (
            lambda: ctx.glue.set_valve(True),
            lambda: ctx.robot.move_linear(Pose(500.0, 0.0, 100.0), 100.0, 1000.0),
        ):
            try:
                await command()
            except asyncio.CancelledError as refusal:
                refused.append(str(refusal))
        await ctx.glue.set_valve(False)  # closing the valve stays allowed
        return {}

    worker = await make_worker(operations={"calibrate_camera": stubborn}, glue=glue, robot=robot)
    await worker.request(Event.CALIBRATE_CAMERA_REQUESTED, source="test")
    await asyncio.wait_for(started.wait(), 5)
    moves = len(robot.moves)
    outcome = await worker.stops.stop(source="test", payload=StopPayload("test"))
    assert outcome.state is State.ERROR
    await asyncio.wait_for(went_on.wait(), 5)
    async with asyncio.timeout(5):
        while len(refused) < 2:
            await asyncio.sleep(0.01)
    assert glue.valve_open is False
    assert len(robot.moves) == moves, "the run moved the arm after the stop"
    assert all("was cancelled" in why for why in refused)


async def test_a_long_queue_of_refusals_lets_the_loop_run_while_it_drains(make_worker) -> None:
    """The worker lets other callbacks (an HTTP handler, the e-stop route) run between
    events: a stop arriving behind a full queue is not kept waiting until it drains."""
    worker = await make_worker()
    queued = [worker.submit(Event.PAUSE_REQUESTED, source="test") for _ in range(1000)]
    left_when_the_loop_ran: list[int] = []
    asyncio.get_running_loop().call_soon(lambda: left_when_the_loop_ran.append(len(worker.queue)))
    outcomes = [await envelope.future for envelope in queued]
    assert not any(outcome.accepted for outcome in outcomes)  # PAUSE in IDLE: refused
    assert left_when_the_loop_ran and left_when_the_loop_ran[0] > 500


async def test_the_idle_a_reset_enters_is_published_without_the_cleared_stop_reason(
    make_worker,
) -> None:
    """The reset's state_changed message (what MQTT keeps retained, OPC UA, the webhooks
    and the state file show) carried the stop reason the reset had just cleared."""
    worker = await make_worker()
    await worker.stops.stop(source="test", payload=StopPayload(reason="guard door"))
    assert worker.view.snapshot()["stop_reason"] is not None
    states = worker.bus.subscribe(10, types=["state_changed"])
    outcome = await worker.request(Event.RESET_REQUESTED, source="test")
    assert outcome.accepted and outcome.state is State.IDLE
    message = await states.get()
    assert message.data["new_state"] == "IDLE"
    assert message.data["snapshot"]["stop_reason"] is None, message.data["snapshot"]
    assert message.data["snapshot"]["error"] is None
