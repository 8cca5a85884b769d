"""The care meter's judgement, pure: from the wear totals and marks to what GET /maintenance
shows.

The totals and marks are what the journal's `wear` table keeps (server/core/worker/care.py
counts them, server/storage/journal/wear.py stores them); the settings are the cell's
`MaintenanceSettings`; `now` is Unix seconds. The running cell's care meter and the
diagnostic bundle (server/diagnostics/bundle.py, which reads the data directory alone,
with no server running) both judge with these functions, so the two cannot disagree.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Final, NamedTuple

from server.settings.maintenance import MaintenanceItem, MaintenanceSettings

# The totals kept, by name: the drivers' counters (care.py: FROM_DRIVERS) and those the
# meter counts itself.
COUNTERS: Final = (
    "valve_cycles",
    "valve_open_s",
    "glue_ml",
    "travel_m",
    "motion_s",
    "camera_frames",
    "parts",
    "purges",
)
LAST_DISPENSE: Final = "mark:last_dispense_at"
REFILLED_AT_ML: Final = "mark:refilled_at_glue_ml"


def done_key(item: str, counter: str) -> str:
    """The mark holding `counter`'s total when `item` was last done."""
    return f"done:{item}:{counter}"


class ItemPlan(NamedTuple):
    """An item's intervals worked out once (they change only with the settings): by
    counter name, and each counter with its interval and the mark of its last done."""

    intervals: dict[str, float]
    counters: tuple[tuple[str, float, str], ...]  # (counter, interval, done_key)


def item_plan(item: MaintenanceItem) -> ItemPlan:
    """The intervals of `item` as the judging below reads them."""
    intervals = item.intervals()
    counters = tuple((c, every, done_key(item.name, c)) for c, every in intervals.items())
    return ItemPlan(intervals, counters)


def _most_used(plan: ItemPlan, values: Mapping[str, float]) -> tuple[float, str, float, float]:
    """The share used of the item's most used interval (percent), that counter ("" when
    none is used), its use and its interval; the last counter wins a tie."""
    worst, which, worst_used, worst_every = 0.0, "", 0.0, 0.0
    get = values.get
    for counter, every, done in plan.counters:
        used = get(counter, 0.0) - get(done, 0.0)
        share = used / every * 100.0
        if share >= worst:
            worst, which, worst_used, worst_every = share, counter, used, every
    return worst, which, worst_used, worst_every


def _status(worst: float, settings: MaintenanceSettings) -> str:
    if worst >= settings.maintenance_overdue_percent:
        return "overdue"
    return "due" if worst >= 100.0 else "ok"


def item_status(plan: ItemPlan, values: Mapping[str, float], settings: MaintenanceSettings) -> str:
    """An item's status alone (`item_state`'s), without building what it shows: the care
    meter asks at every check and every run's end, so the share is found inline."""
    worst, get = 0.0, values.get
    for counter, every, done in plan.counters:
        share = (get(counter, 0.0) - get(done, 0.0)) / every * 100.0
        if share > worst:
            worst = share
    if worst >= settings.maintenance_overdue_percent:
        return "overdue"
    return "due" if worst >= 100.0 else "ok"


def item_state(
    item: MaintenanceItem,
    values: Mapping[str, float],
    settings: MaintenanceSettings,
    plan: ItemPlan | None = None,
) -> dict[str, Any]:
    """An item's status (ok, due at 100 % of any interval, overdue past
    maintenance_overdue_percent), the share used of its most used interval, and which.
    `plan` is the item's `item_plan`, when the caller keeps it."""
    plan = plan if plan is not None else item_plan(item)
    worst, counter, used, every = _most_used(plan, values)
    return {
        "name": item.name,
        "status": _status(worst, settings),
        "percent": round(worst, 1),
        "reason": f"{counter} {used:g} of {every:g}" if counter else "",
        "intervals": plan.intervals,
        "done_at": values.get(f"done_at:{item.name}"),
    }


def pot_status(values: Mapping[str, float], settings: MaintenanceSettings, now: float) -> str:
    """`pot_life`'s status alone (off, ok, near, expired), without its message."""
    last = values.get(LAST_DISPENSE)
    if settings.pot_life_minutes is None:
        return "off"
    if last is None:
        return "ok"
    share = max(0.0, now - last) / (settings.pot_life_minutes * 60.0) * 100.0
    if share >= 100.0:
        return "expired"
    return "near" if share >= settings.pot_life_warning_percent else "ok"


def pot_life(
    values: Mapping[str, float], settings: MaintenanceSettings, now: float
) -> dict[str, Any]:
    """The open time since the last dispense against the adhesive's pot life."""
    last = values.get(LAST_DISPENSE)
    if settings.pot_life_minutes is None or last is None:
        return {"status": "off" if settings.pot_life_minutes is None else "ok", "open_s": None}
    limit = settings.pot_life_minutes * 60.0
    open_s = max(0.0, now - last)
    share = open_s / limit * 100.0
    message = (
        f"the glue in the line has been open {open_s / 60:.1f} min of its "
        f"{settings.pot_life_minutes:g} min pot life: purge the line"
        + (" before the next start (starts are refused until then)" if share >= 100 else "")
    )
    return {
        "status": pot_status(values, settings, now),
        "open_s": round(open_s, 1),
        "percent": round(share, 1),
        "message": message,
    }


def glue_status(values: Mapping[str, float], settings: MaintenanceSettings) -> str:
    """`glue_level`'s status alone (off, ok, low), without its message."""
    if settings.glue_reservoir_ml is None:
        return "off"
    used = values.get("glue_ml", 0.0) - values.get(REFILLED_AT_ML, 0.0)
    level = max(0.0, settings.glue_reservoir_ml - used)
    percent = level / settings.glue_reservoir_ml * 100.0
    return "low" if percent <= settings.glue_low_level_percent else "ok"


def glue_level(values: Mapping[str, float], settings: MaintenanceSettings) -> dict[str, Any]:
    """The reservoir's estimated level from the glue dispensed since the last refill."""
    if settings.glue_reservoir_ml is None:
        return {"status": "off", "level_ml": None}
    used = values.get("glue_ml", 0.0) - values.get(REFILLED_AT_ML, 0.0)
    level = max(0.0, settings.glue_reservoir_ml - used)
    percent = level / settings.glue_reservoir_ml * 100.0
    message = (
        f"the glue reservoir is at about {level:.0f} ml ({percent:.0f} %) by the glue "
        "dispensed since its last refill: refill it, then POST /glue/refill"
    )
    return {
        "status": glue_status(values, settings),
        "level_ml": round(level, 1),
        "percent": round(percent, 1),
        "message": message,
    }


def state_of(
    values: Mapping[str, float], settings: MaintenanceSettings, now: float
) -> dict[str, Any]:
    """What GET /maintenance shows: the counters (hours as hours), each item, the pot
    life and the glue level."""
    counters = {name: round(values.get(name, 0.0), 3) for name in COUNTERS}
    counters["valve_open_hours"] = round(counters.pop("valve_open_s") / 3600.0, 4)
    counters["motion_hours"] = round(counters.pop("motion_s") / 3600.0, 4)
    return {
        "counters": counters,
        "items": [item_state(item, values, settings) for item in settings.maintenance_items],
        "pot_life": pot_life(values, settings, now),
        "glue_level": glue_level(values, settings),
    }
