"""The shift reports' timer and its catch-up after a restart, on the simulated cell's real
journal, with the wall clock replaced: the report of a shift is made when the clock
passes its end (and the day's with the day's last shift), and a server that was down at
a shift's end makes that shift's report when it starts, once, and only for a shift it
ran in."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

from server.views.reports import DAY_S, ShiftReports, shift_at, utc_offset
from tests.rig import Rig, open_rig

CELL = "cell-t"
SHIFT_HOURS = 8.0


class SteppedClock:
    """A wall clock that jumps ahead by each wait asked of it, up to `until`; a wait that
    would pass `until` never ends (the test then stops the reports)."""

    def __init__(self, now: float, until: float) -> None:
        self.now = now
        self.until = until
        self.waits: list[float] = []

    def time(self) -> float:
        return self.now

    async def sleep(self, seconds: float) -> None:
        self.waits.append(seconds)
        if self.now + seconds > self.until:
            await asyncio.Event().wait()
        self.now += seconds
        await asyncio.sleep(0)


def last_shift_of_the_day_hour(now: float) -> int:
    """A day start that puts `now` in the day's last 8-hour shift: the next full hour."""
    return (time.localtime(now).tm_hour + 1) % 24


def reports(rig: Rig, kind: str) -> list[dict[str, Any]]:
    assert rig.cell.journal is not None
    return rig.cell.journal.query("reports", filters={"kind": kind}, limit=10)


def timer(rig: Rig, clock: SteppedClock, start_hour: int) -> ShiftReports:
    assert rig.cell.journal is not None
    return ShiftReports(
        rig.cell,
        rig.cell.journal,
        CELL,
        lambda: SHIFT_HOURS,
        start_hour,
        care=rig.cell.worker.care.state,
        clock=clock.time,
        sleep=clock.sleep,
    )


async def made(rig: Rig, kind: str, count: int) -> list[dict[str, Any]]:
    for _ in range(500):
        assert rig.cell.journal is not None
        await rig.cell.journal.caught_up()
        found = reports(rig, kind)
        if len(found) >= count:
            return found
        await asyncio.sleep(0.01)
    raise AssertionError(f"{count} {kind} report(s) not made: {reports(rig, kind)}")


async def test_the_shift_and_the_day_are_reported_when_the_clock_passes_their_end(
    tmp_path: Path,
) -> None:
    async with open_rig(tmp_path / "data", cell_id=CELL) as rig:
        now = time.time()  # the rig's start is on record in this shift
        start_hour = last_shift_of_the_day_hour(now)
        shift = shift_at(now, SHIFT_HOURS, start_hour, utc_offset(now))
        assert shift.ends_day
        clock = SteppedClock(now, until=shift.end + 1.0)
        reports_ = timer(rig, clock, start_hour)
        reports_.start()
        try:
            shifts, days = await made(rig, "shift", 1), await made(rig, "day", 1)
        finally:
            await reports_.stop()
        assert [(r["window_start"], r["window_end"]) for r in shifts] == [(shift.start, shift.end)]
        assert [(r["window_start"], r["window_end"]) for r in days] == [
            (shift.end - DAY_S, shift.end)
        ]
        # it looked at least once a minute, and made the report no earlier than the end
        assert max(clock.waits) <= 60.0 and len(clock.waits) >= (shift.end - now) / 60.0
        assert shifts[0]["time"] >= shift.end

        # Started again after that end: the shift has its report, so none is made twice.
        clock = SteppedClock(shift.end + 60.0, until=shift.end + 60.0)
        again = timer(rig, clock, start_hour)
        again.start()
        await asyncio.sleep(0.2)
        await again.stop()
        assert rig.cell.journal is not None
        await rig.cell.journal.caught_up()
        assert len(reports(rig, "shift")) == 1


async def test_a_shift_the_server_ran_in_but_missed_the_end_of_is_reported_at_the_next_start(
    tmp_path: Path,
) -> None:
    async with open_rig(tmp_path / "data", cell_id=CELL) as rig:
        now = time.time()
        start_hour = last_shift_of_the_day_hour(now)
        shift = shift_at(now, SHIFT_HOURS, start_hour, utc_offset(now))

        # A day later, the shift before the start had no transition: nothing to report.
        later = SteppedClock(shift.end + DAY_S, until=shift.end + DAY_S)
        idle = timer(rig, later, start_hour)
        idle.start()
        await asyncio.sleep(0.2)
        await idle.stop()

        # A minute into the next shift: the server ran in the last one and missed its end.
        clock = SteppedClock(shift.end + 60.0, until=shift.end + 60.0)
        reports_ = timer(rig, clock, start_hour)
        reports_.start()
        try:
            shifts = await made(rig, "shift", 1)
        finally:
            await reports_.stop()
        assert [(r["window_start"], r["window_end"]) for r in shifts] == [(shift.start, shift.end)]
        assert reports(rig, "day") == []  # the catch-up makes the shift's only
