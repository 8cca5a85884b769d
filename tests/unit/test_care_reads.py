"""The care meter's reads at each check and run's end pass over what did not change (a
device's details as they were, the totals as judged, the totals as written), and still
see every change: a counter grown, a setting changed in place, a total changed."""

from __future__ import annotations

from typing import Any

from server.core.worker import care_rules as rules
from server.core.worker.runs import RunEnded
from server.drivers import wear
from server.settings.maintenance import MaintenanceItem
from tests.fakes import FakeGlue, FakeRobot


def ended(parts: int) -> RunEnded:
    return RunEnded("r", "trajectory", "completed", 1.0, "EXECUTING_TRAJECTORY", {}, None, parts)


class CountingJournal:
    """Wraps the worker's journal and keeps every list of records the care meter appends."""

    def __init__(self, journal: Any) -> None:
        self.journal = journal
        self.appended: list[list[Any]] = []

    def append(self, records: list[Any], *, durable: bool = True) -> Any:
        self.appended.append(records)
        return self.journal.append(records, durable=durable)


async def test_counters_grown_between_reads_are_all_counted(make_worker) -> None:
    glue, robot = FakeGlue(), FakeRobot()
    worker = await make_worker(glue=glue, robot=robot)
    care = worker.care
    care.check()
    care.check()  # nothing grew: both devices' details are passed over
    wear.add(glue.health.details, wear.GLUE_ML, 2.5)
    care.check()
    care.check()
    wear.add(glue.health.details, wear.GLUE_ML, 1.5)
    wear.add(robot.health.details, wear.TRAVEL_M, 3.0)
    care.check()
    assert care.values["glue_ml"] == 4.0 and care.values["travel_m"] == 3.0
    robot.health.details["position"] = [1.0, 2.0, 3.0]  # another key: no counter grew
    care.check()
    assert care.values["travel_m"] == 3.0


async def test_an_overdue_percent_changed_in_place_is_judged_at_the_next_check(
    make_worker, fast_settings
) -> None:
    """The statuses judged are kept while the totals and schedule are the same; the
    overdue share is read again (PATCH /settings changes it on the same settings)."""
    items = (MaintenanceItem(name="clean nozzle", every_parts=10),)
    settings = fast_settings.model_copy(
        update={"maintenance_items": items, "maintenance_overdue_percent": 150.0}
    )
    worker = await make_worker(settings)
    care = worker.care
    care.run_ended(ended(13))  # 130 %: due, not yet overdue
    assert "due:clean nozzle" in care._raised
    assert "overdue:clean nozzle" not in care._raised
    care.check()  # the same totals: the same statuses
    assert "overdue:clean nozzle" not in care._raised
    settings.maintenance_overdue_percent = 120.0
    care.check()
    assert care._raised.get("overdue:clean nozzle") == "MAINTENANCE_OVERDUE"


async def test_a_run_end_writes_only_the_totals_changed_and_nothing_when_none(
    make_worker,
) -> None:
    worker = await make_worker()
    care = worker.care
    journal = CountingJournal(care.journal)
    care.journal = journal
    care.run_ended(ended(2))  # a fresh journal: every total is written the first time
    assert [len(records) for records in journal.appended] == [len(care.values)]
    care.run_ended(ended(0))  # nothing changed: nothing written
    assert len(journal.appended) == 1
    care.run_ended(ended(1))
    assert [len(records) for records in journal.appended[1:]] == [1]  # parts
    care.stop()  # the last write: every key
    assert len(journal.appended[-1]) == len(care.values)


async def test_a_check_on_the_totals_as_judged_judges_no_item_again(
    make_worker, fast_settings, monkeypatch
) -> None:
    """Each run's end checks the schedule: with the totals, the schedule and the overdue
    share those of the last check, the items' statuses are those it found."""
    items = (MaintenanceItem(name="clean nozzle", every_parts=10),)
    worker = await make_worker(fast_settings.model_copy(update={"maintenance_items": items}))
    care = worker.care
    care.run_ended(ended(3))
    judged: list[Any] = []
    item_status = rules.item_status

    def counted(*args: Any) -> str:
        judged.append(args)
        return item_status(*args)

    monkeypatch.setattr(rules, "item_status", counted)
    care.run_ended(ended(0))
    care.check()
    assert judged == []
    care.run_ended(ended(1))  # a part more: judged again
    assert len(judged) == 1
