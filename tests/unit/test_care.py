"""The care meter and the purge on fakes: the schedule's judgement, warnings raised once,
done and refill, pot life; and a purge never opening the valve after a stop."""

from __future__ import annotations

import asyncio
from typing import Any

from server.core.machine.transitions import Event, State
from server.core.worker.runs import RunEnded
from server.drivers import wear
from server.settings.maintenance import MaintenanceItem
from tests.conftest import START_PAYLOAD
from tests.fakes import FakeClock, FakeGlue, FakeRobot


def ended(parts: int) -> RunEnded:
    return RunEnded("r", "trajectory", "completed", 1.0, "EXECUTING_TRAJECTORY", {}, None, parts)


def alerts_of(worker: Any) -> list[str]:
    return [
        row["code"]
        for row in worker.recorder.journal.query("errors", limit=1000)
        if row["classification"] == "warning"
    ]


async def test_an_item_is_due_at_its_interval_overdue_past_it_and_warned_once(
    make_worker, fast_settings
) -> None:
    items = (MaintenanceItem(name="clean nozzle", every_parts=4, every_ml=500.0),)
    settings = fast_settings.model_copy(update={"maintenance_items": items})
    worker = await make_worker(settings)
    care = worker.care
    for _ in range(3):
        care.run_ended(ended(1))
    assert care.state()["items"][0]["status"] == "ok"
    care.run_ended(ended(1))
    care.run_ended(ended(0))  # a run that made no part: no new warning
    assert care.state()["items"][0]["status"] == "due"
    await worker.recorder.journal.caught_up()
    assert alerts_of(worker).count("MAINTENANCE_DUE") == 1
    care.run_ended(ended(1))  # 5 of 4: 125 %, past the 120 % overdue share
    assert care.state()["items"][0]["status"] == "overdue"
    done = care.done("Clean Nozzle")
    assert done["status"] == "ok" and done["percent"] == 0.0
    care.run_ended(ended(4))
    await worker.recorder.journal.caught_up()
    codes = alerts_of(worker)
    assert codes.count("MAINTENANCE_OVERDUE") == 1 and codes.count("MAINTENANCE_DUE") == 2


async def test_glue_counted_by_the_driver_empties_the_reservoir_until_a_refill(
    make_worker, fast_settings
) -> None:
    settings = fast_settings.model_copy(
        update={"glue_reservoir_ml": 100.0, "glue_low_level_percent": 20.0}
    )
    glue = FakeGlue()
    worker = await make_worker(settings, glue=glue)
    wear.add(glue.health.details, wear.GLUE_ML, 85.0)
    worker.care.check()
    level = worker.care.glue_level()
    assert level["status"] == "low" and level["level_ml"] == 15.0
    assert worker.care.refill()["level_ml"] == 100.0
    wear.add(glue.health.details, wear.GLUE_ML, 10.0)
    assert worker.care.state()["glue_level"]["level_ml"] == 90.0


async def test_pot_life_warns_near_its_end_and_refuses_a_start_after_it(
    make_worker, fast_settings
) -> None:
    clock = FakeClock()
    settings = fast_settings.model_copy(update={"pot_life_minutes": 10.0})
    glue = FakeGlue()
    worker = await make_worker(settings, glue=glue, clock=clock)
    wear.add(glue.health.details, wear.VALVE_CYCLES, 1)  # glue flowed
    worker.care.check()
    await clock.advance(8.5 * 60)
    worker.care.check()
    assert worker.care.pot_life()["status"] == "near"
    await clock.advance(2 * 60)
    outcome = await worker.request(Event.START_REQUESTED, source="test", payload=START_PAYLOAD)
    assert not outcome.accepted and "purge" in outcome.message, outcome.message
    assert worker.ctx.state is State.IDLE


async def test_a_stop_during_the_purges_move_keeps_the_valve_closed(
    make_worker, fast_settings
) -> None:
    """The robot's stop ends the move normally on this fake: without the check of the
    stops before the valve opens, the purge would go on to open it after the halt."""
    robot = FakeRobot(speed_factor=0.01)  # the move to the purge position takes minutes
    glue = FakeGlue()
    worker = await make_worker(fast_settings, robot=robot, glue=glue)
    outcome = await worker.request(Event.PURGE_REQUESTED, source="test")
    assert outcome.accepted and outcome.state is State.IDLE
    async with asyncio.timeout(5):
        while not robot.moving:
            await asyncio.sleep(0.005)
    await worker.stops.stop(source="test")
    assert worker.ctx.state is State.ERROR
    async with asyncio.timeout(5):
        while worker.activities.purging:
            await asyncio.sleep(0.005)
    await asyncio.sleep(0.05)  # anything the purge had left to send
    assert [opened for _, opened in glue.valve_log if opened] == []
    assert glue.valve_open is False


async def said_on_the_bus(subscription: Any) -> list[tuple[str, str]]:
    """The warnings raised and cleared so far, from the bus, in order."""
    said = []
    for _ in range(5):  # delivery is spread over turns of the loop
        await asyncio.sleep(0)
    while subscription.pending:
        message = await subscription.get()
        said.append((message.type, message.data["code"]))
    return said


async def test_a_care_warning_is_cleared_when_its_cause_goes(make_worker, fast_settings) -> None:
    """An item done, a refill, glue flowing again: each warning it ended is cleared on the
    bus (`alert_cleared`), once no item still holds its code."""
    clock = FakeClock()
    items = (
        MaintenanceItem(name="clean nozzle", every_parts=3),
        MaintenanceItem(name="check hose", every_parts=3),
    )
    settings = fast_settings.model_copy(
        update={
            "maintenance_items": items,
            "glue_reservoir_ml": 100.0,
            "glue_low_level_percent": 20.0,
            "pot_life_minutes": 10.0,
        }
    )
    glue = FakeGlue()
    worker = await make_worker(settings, glue=glue, clock=clock)
    care = worker.care
    bus = worker.bus.subscribe(100, ["alert", "alert_cleared"])
    care.run_ended(ended(3))  # both items due: one code
    wear.add(glue.health.details, wear.GLUE_ML, 90.0)  # glue flowed: the reservoir low
    care.check()
    assert await said_on_the_bus(bus) == [
        ("alert", "MAINTENANCE_DUE"),
        ("alert", "MAINTENANCE_DUE"),
        ("alert", "GLUE_LEVEL_LOW"),
    ]
    care.done("clean nozzle")  # the hose is still due: the code stays raised
    assert await said_on_the_bus(bus) == []
    care.done("check hose")
    assert await said_on_the_bus(bus) == [("alert_cleared", "MAINTENANCE_DUE")]
    care.refill()
    assert await said_on_the_bus(bus) == [("alert_cleared", "GLUE_LEVEL_LOW")]
    await clock.advance(9 * 60)
    care.check()
    assert await said_on_the_bus(bus) == [("alert", "POT_LIFE_NEAR")]
    wear.add(glue.health.details, wear.VALVE_CYCLES, 1)  # a purge or a run dispensed
    care.check()
    assert await said_on_the_bus(bus) == [("alert_cleared", "POT_LIFE_NEAR")]
    care.check()
    assert await said_on_the_bus(bus) == []


async def test_a_run_end_with_nothing_to_warn_of_builds_no_presentation(
    make_worker, fast_settings, monkeypatch
) -> None:
    """Every run's end checks the schedule, the pot life and the level: judged by their
    statuses alone, the dicts GET /maintenance shows are built only for a warning."""
    settings = fast_settings.model_copy(
        update={"pot_life_minutes": 10.0, "glue_reservoir_ml": 100.0}
    )
    glue = FakeGlue()
    worker = await make_worker(settings, glue=glue)
    wear.add(glue.health.details, wear.VALVE_CYCLES, 1)  # glue flowed: the pot life runs

    def built(*_: Any, **__: Any) -> Any:
        raise AssertionError("a presentation was built for a check that warns of nothing")

    for name in ("item_state", "pot_life", "glue_level"):
        monkeypatch.setattr(f"server.core.worker.care_rules.{name}", built)
    worker.care.run_ended(ended(1))
    assert worker.care.start_problem() is None


async def test_a_due_warning_says_which_interval_and_a_new_schedule_is_judged_at_once(
    make_worker, fast_settings
) -> None:
    """The warning's message names the most used interval; a schedule changed in force
    (PATCH /settings assigns a new one) is the one the next check judges."""
    items = (MaintenanceItem(name="clean nozzle", every_parts=4, every_ml=500.0),)
    settings = fast_settings.model_copy(update={"maintenance_items": items})
    worker = await make_worker(settings)
    care = worker.care
    care.run_ended(ended(2))
    await worker.recorder.journal.caught_up()
    assert "MAINTENANCE_DUE" not in alerts_of(worker)  # 2 of 4 parts
    settings.maintenance_items = (MaintenanceItem(name="clean nozzle", every_parts=2),)
    care.run_ended(ended(0))
    await worker.recorder.journal.caught_up()
    rows = [
        row["message"]
        for row in worker.recorder.journal.query("errors", limit=1000)
        if row["code"] == "MAINTENANCE_DUE"
    ]
    assert rows == [
        "maintenance due: clean nozzle (parts 2 of 2); when done, POST /maintenance/clean "
        "nozzle/done"
    ]
