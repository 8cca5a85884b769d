"""Shift and daily reports: what a window of the journal says about production.

A report is built from the same rows and the same arithmetic as GET /kpis
(`kpi_query.kpis_of`), so its figures agree with the dashboard's for the same
window, plus what a shift leader reads first: parts good and defective, hour by
hour; OEE and its factors; the stop reasons that cost the most time; the alerts
(warnings) raised; and the maintenance due when it was made (the care meter's
items that are due or overdue, pot life and glue level, server/core/worker/care.py).

`ShiftReports` makes one at the end of every shift and of every production day
(`shift_start_hour`, `shift_hours`), stores it in the journal's `reports` table
and publishes it on the bus as a `report` record, which the webhooks
(server/notify/) and the MQTT link (`report` topic, retained) pass on. A server
that was down at a shift's end makes that shift's report when it starts.

Shift boundaries are in the server's local time: a production day starts at
`shift_start_hour` and is cut into shifts of `shift_hours` (the last one of the
day shorter when they do not divide 24 h). The offset from UTC is the one in
force at the time asked, so a day across a daylight-saving change is an hour
longer or shorter in its last shift.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import time
from collections import defaultdict
from collections.abc import Awaitable, Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

from server.core.infra.bus import Bus
from server.core.machine.transitions import State
from server.quality.part_verdict import inspection_of
from server.storage.journal import Journal, records
from server.views.kpi_query import KPI_ROW_LIMIT, RunningCell, kpis_of
from server.views.kpis import COUNTED_CLASSIFICATIONS, Window

log = logging.getLogger(__name__)

DAY_S = 86_400.0
TOP_STOPS = 5


@dataclass(frozen=True, slots=True)
class Shift:
    """A window a report covers, and whether it ends a production day too."""

    start: float
    end: float
    ends_day: bool
    day_start: float


def utc_offset(at: float) -> float:
    """The server's local offset from UTC (seconds) in force at Unix time `at`."""
    return float(time.localtime(at).tm_gmtoff)


def shift_at(now: float, shift_hours: float, start_hour: float, offset_s: float) -> Shift:
    """The shift under way at `now` (pure: the offset from UTC is given)."""
    first = start_hour * 3600.0
    day_start = math.floor((now + offset_s - first) / DAY_S) * DAY_S + first - offset_s
    length = shift_hours * 3600.0
    k = math.floor((now - day_start) / length)
    start = day_start + k * length
    end = min(start + length, day_start + DAY_S)
    return Shift(start, end, end >= day_start + DAY_S, day_start)


def stop_reasons(
    transitions: Iterable[Mapping[str, Any]],
    faults: Mapping[str, Mapping[str, Any]],
    window: Window,
    *,
    current_state: str,
    current_since: float,
    now: float,
) -> list[dict[str, Any]]:
    """The faults that stopped the cell in `window`, by code, with the time spent in ERROR
    after each (clipped to the window), most time first.

    `transitions` oldest first; `faults` the first fault each event recorded, by event id.
    Each stay in ERROR is charged to the fault of the event that entered it.
    """
    seconds: dict[str, float] = defaultdict(float)
    counts: dict[str, int] = defaultdict(int)
    about: dict[str, Mapping[str, Any]] = {}
    entered_by: str | None = None
    error = State.ERROR.value
    for row in transitions:
        if row["old_state"] == error and entered_by is not None:
            begin = float(row["time"]) - float(row["time_in_old_state"])
            seconds[entered_by] += window.overlap(begin, float(row["time"]))
        if row["new_state"] == error and row["old_state"] != error:
            fault = faults.get(str(row["event_id"]))
            entered_by = str(fault["code"]) if fault else str(row["event"])
            about.setdefault(entered_by, fault or {"component": "", "message": row["event"]})
            if window.contains(float(row["time"])):
                counts[entered_by] += 1
        elif row["old_state"] == error:
            entered_by = None
    if current_state == error and entered_by is not None:
        seconds[entered_by] += window.overlap(current_since, now)
    codes = [code for code in set(seconds) | set(counts) if seconds[code] > 0 or counts[code]]
    codes.sort(key=lambda code: (-seconds[code], -counts[code], code))
    return [
        {
            "code": code,
            "component": about[code].get("component", ""),
            "message": about[code].get("message", ""),
            "count": counts[code],
            "seconds": round(seconds[code], 3),
        }
        for code in codes[:TOP_STOPS]
    ]


def alerts_of(errors: Iterable[Mapping[str, Any]]) -> dict[str, Any]:
    """The warnings raised (errors rows classed `warning`), counted by code, most first."""
    by_code: dict[str, dict[str, Any]] = {}
    for row in errors:
        if row["classification"] != "warning":
            continue
        entry = by_code.setdefault(
            row["code"], {"code": row["code"], "component": row["component"], "count": 0}
        )
        entry["count"] += 1
        entry["last_message"] = row["message"]
    listed = sorted(by_code.values(), key=lambda e: (-e["count"], e["code"]))
    return {"count": sum(e["count"] for e in listed), "by_code": listed}


def parts_by_hour(operations: Iterable[Mapping[str, Any]], window: Window) -> list[dict[str, Any]]:
    """Parts judged good and defective per hour of the window (by when their run ended)."""
    hours = max(1, math.ceil(window.seconds / 3600.0 - 1e-9))
    slots = [{"start": window.start + 3600.0 * h, "good": 0, "defective": 0} for h in range(hours)]
    for row in operations:
        ended = row.get("ended_at")
        if row.get("kind") != "trajectory" or not window.contains(ended):
            continue
        inspection = inspection_of(row.get("result"))
        verdict = inspection.get("verdict") if inspection else None
        if verdict in ("good", "defective"):
            at = float(ended) if ended is not None else window.start
            slots[min(hours - 1, int((at - window.start) // 3600.0))][verdict] += 1
    return slots


def maintenance_due(care: Mapping[str, Any]) -> dict[str, Any]:
    """What of the care meter's state (GET /maintenance) a report carries: the items due
    or overdue, and pot life and glue level when they are watched."""
    return {
        "items_due": [
            {k: item[k] for k in ("name", "status", "percent", "reason")}
            for item in care.get("items", [])
            if item["status"] != "ok"
        ],
        "pot_life": care.get("pot_life", {}).get("status", "off"),
        "glue_level": care.get("glue_level", {}).get("status", "off"),
    }


async def build_report(
    cell: RunningCell,
    window: Window,
    kind: str,
    cell_id: str,
    now: float | None = None,
    care: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The report of `window` (`kind`: its period, `shift` or `day`), from the journal;
    `care` is the care meter's state when it is made (GET /maintenance's answer)."""
    journal = cell.journal
    assert journal is not None, "the cell is not started"
    kpis = await kpis_of(cell, window.start, window.end)
    now = time.time() if now is None else now
    state, since = cell.view.state.value, cell.view.since

    def read() -> dict[str, Any]:
        transitions = journal.query(
            "transitions", since=window.start, limit=KPI_ROW_LIMIT, newest_first=False
        )
        before = journal.query("transitions", until=window.start, limit=1)
        errors = journal.query(
            "errors", since=window.start - DAY_S, until=window.end, limit=KPI_ROW_LIMIT
        )
        first: dict[str, dict[str, Any]] = {}
        for row in sorted(errors, key=lambda r: r["seq"]):
            if row["classification"] in COUNTED_CLASSIFICATIONS:
                first.setdefault(row["event_id"], row)
        operations = journal.query(
            "operations",
            since=window.start - DAY_S,
            until=window.end,
            limit=KPI_ROW_LIMIT,
            newest_first=False,
        )
        for row in operations:
            row["result"] = _decoded(row.get("result"))
        stops = stop_reasons(
            [*before, *transitions],
            first,
            window,
            current_state=state,
            current_since=since,
            now=min(now, window.end),
        )
        in_window = [e for e in errors if window.contains(e["time"])]
        return {
            "stops": stops,
            "alerts": alerts_of(in_window),
            "hours": parts_by_hour(operations, window),
        }

    found = await asyncio.to_thread(read)
    quality = kpis.get("quality") or {}
    return {
        "period": kind,
        "cell_id": cell_id,
        "window": {"start": window.start, "end": window.end},
        "generated_at": now,
        "parts": {
            "good": quality.get("parts_good", 0),
            "defective": quality.get("parts_defective", 0),
            "processed": kpis.get("workpieces_processed", 0),
            "failed": kpis.get("workpieces_failed", 0),
            "by_hour": found["hours"],
        },
        "oee": kpis.get("oee"),
        "time_in_state_s": kpis.get("time_in_state_s"),
        "operations_completed_per_hour": kpis.get("operations_completed_per_hour"),
        "error_rate_per_100_operations": kpis.get("error_rate_per_100_operations"),
        "mtbf_s": kpis.get("mtbf_s"),
        "mttr_s": kpis.get("mttr_s"),
        "stop_reasons": found["stops"],
        "alerts": found["alerts"],
        "maintenance": maintenance_due(care or {}),
    }


def _decoded(text: Any) -> Any:
    if not isinstance(text, str):
        return text
    try:
        return json.loads(text)
    except ValueError:
        return None


class _Cell(RunningCell, Protocol):
    @property
    def bus(self) -> Bus: ...


class ShiftReports:
    """Makes, stores and publishes the report of each shift and day as it ends."""

    def __init__(
        self,
        cell: _Cell,
        journal: Journal,
        cell_id: str,
        shift_hours: Callable[[], float],
        start_hour: float,
        care: Callable[[], Mapping[str, Any]] | None = None,
        clock: Callable[[], float] = time.time,
        sleep: Callable[[float], Awaitable[None]] = asyncio.sleep,
    ) -> None:
        """`care` gives the care meter's state for a report's maintenance; `clock` and
        `sleep` are the wall clock and the wait between looks (a test gives its own)."""
        self.cell = cell
        self.care = care
        self.clock = clock
        self.sleep = sleep
        self.journal = journal
        self.cell_id = cell_id
        self.shift_hours = shift_hours
        self.start_hour = start_hour
        self._task: asyncio.Task[None] | None = None

    def start(self) -> None:
        if self._task is None:
            self._task = asyncio.create_task(self._run(), name="shift-reports")

    async def stop(self) -> None:
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            await asyncio.wait({task})

    def shift_at(self, now: float) -> Shift:
        return shift_at(now, self.shift_hours(), self.start_hour, utc_offset(now))

    async def make(self, window: Window, kind: str) -> dict[str, Any]:
        """Build the report of `window`, journal it (durably) and publish it; the report
        with its id."""
        document = await build_report(
            self.cell,
            window,
            kind,
            self.cell_id,
            now=self.clock(),
            care=self.care() if self.care is not None else None,
        )
        record = records.report(
            time=document["generated_at"],
            kind=kind,
            window_start=window.start,
            window_end=window.end,
            document=document,
        )
        written = self.journal.append([record])
        if written is not None:
            await written
        stored = await asyncio.to_thread(self._find, kind, window.end)
        document = {"id": stored, **document}
        # On the bus (and so to webhooks and MQTT) `id` is `report_id`: a notice's own id
        # is its delivery's.
        published = {k: v for k, v in document.items() if k != "id"}
        self.cell.bus.publish(
            "report", {"report_id": stored, **published, "time": document["generated_at"]}
        )
        log.info("%s report %s made for %s", kind, stored, _span(window))
        return document

    def _find(self, kind: str, end: float) -> int | None:
        rows = self.journal.query("reports", filters={"kind": kind}, until=end + DAY_S, limit=20)
        for row in rows:
            if row["window_end"] == end:
                return int(row["seq"])
        return None

    async def _run(self) -> None:
        try:
            await self._catch_up()
        except Exception:  # a report is bookkeeping: it never stops the cell
            log.exception("the missed shift report could not be made")
        shift = self.shift_at(self.clock())
        while True:
            # A minute at most between looks: a clock set forward (NTP after a cold start),
            # or shift_hours changed at run time (PATCH /settings), is seen within a minute.
            await self.sleep(min(60.0, max(0.0, shift.end - self.clock())))
            now = self.clock()
            if now >= shift.end:
                try:
                    await self.make(Window(shift.start, shift.end), "shift")
                    if shift.ends_day:
                        await self.make(Window(shift.end - DAY_S, shift.end), "day")
                except Exception:  # a report is bookkeeping: it never stops the cell
                    log.exception("the report of the shift ending %s could not be made", shift.end)
            shift = self.shift_at(now)

    async def _catch_up(self) -> None:
        """The last shift's report, when the server was down at its end."""
        now = self.clock()
        current = self.shift_at(now)
        last = self.shift_at(current.start - 1e-3)
        if await asyncio.to_thread(self._find, "shift", last.end) is None:
            ran = await asyncio.to_thread(
                self.journal.count, "transitions", since=last.start, until=last.end
            )
            if ran:  # the server ran in that shift and stopped before its end
                await self.make(Window(last.start, last.end), "shift")


def _span(window: Window) -> str:
    def clock(t: float) -> str:
        return time.strftime("%Y-%m-%d %H:%M", time.localtime(t))

    return f"{clock(window.start)} to {clock(window.end)}"
