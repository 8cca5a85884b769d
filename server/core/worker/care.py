"""The cell's wear and the glue line's care: counters, the maintenance schedule, pot life, level.

Wear is counted by the drivers as they work (`server/drivers/wear.py`: valve
openings, open time and glue dispensed, robot travel and motion time, camera
frames); `CareMeter` reads what grew every care_check_interval, adds it to the
totals the journal keeps (table `wear`) and counts what the drivers cannot see:
parts sprayed (a completed trajectory run's workpieces) and purges. It never
blocks the worker: the totals live in memory, and are written (one replace per
key, not awaited) every wear_persist_interval, at each run's end and at a clean
stop; a crash loses at most one interval of wear.

From the totals it judges, at each check:

- each maintenance item (settings) is `ok`, `due` (100 % of any interval used)
  or `overdue` (maintenance_overdue_percent); `done` restarts its intervals;
- the adhesive's pot life since the last dispense (a run's glue or a purge):
  a warning at pot_life_warning_percent, and past it `start_problem` refuses a
  start until a purge;
- the reservoir's level, estimated from the glue dispensed since the last
  `refill`, with a warning at glue_low_level_percent.

Each warning is raised once as its condition begins, through `Alerts.warn`:
logged, journaled as a warning, and on the bus as an `alert` (the WebSocket,
MQTT, OPC UA alarm events and webhooks all take it from there). Each check also
finds the warnings whose condition no longer holds (an item done or its interval
changed, glue dispensed again, a refill) and says so through `Alerts.cleared`, an
`alert_cleared` naming the code once no item still holds it (MAINTENANCE_DUE is one
code for every item due), so OPC UA's alarm condition goes inactive. The judging
itself is pure (care_rules.py), shared with the diagnostic bundle.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

from server.core.infra.clock import Clock, Timer
from server.core.worker import care_rules as rules
from server.core.worker.alerts import Alerts
from server.core.worker.devices import CellDevices
from server.core.worker.runs import RunEnded
from server.drivers import wear
from server.settings.maintenance import MaintenanceItem, MaintenanceSettings
from server.storage.journal import Journal
from server.storage.journal import wear as wear_table

log = logging.getLogger(__name__)

# The totals kept, each from a driver's counter (device, health.details key) or counted here.
FROM_DRIVERS = {
    "valve_cycles": ("glue", wear.VALVE_CYCLES),
    "valve_open_s": ("glue", wear.VALVE_OPEN_S),
    "glue_ml": ("glue", wear.GLUE_ML),
    "travel_m": ("robot", wear.TRAVEL_M),
    "motion_s": ("robot", wear.MOTION_S),
    "camera_frames": ("camera", wear.FRAMES),
}
COUNTERS = (*FROM_DRIVERS, "parts", "purges")
# FROM_DRIVERS by device, in its order, for `read_drivers`.
_GLUE_COUNTERS, _ROBOT_COUNTERS, _CAMERA_COUNTERS = (
    tuple((name, key) for name, (of, key) in FROM_DRIVERS.items() if of == device)
    for device in ("glue", "robot", "camera")
)
assert (*_GLUE_COUNTERS, *_ROBOT_COUNTERS, *_CAMERA_COUNTERS) == tuple(
    (name, key) for name, (_, key) in FROM_DRIVERS.items()
), "FROM_DRIVERS lists each device's counters together: glue, robot, camera"
assert COUNTERS == rules.COUNTERS, "care_rules.COUNTERS names the same totals"
LAST_DISPENSE = rules.LAST_DISPENSE
REFILLED_AT_ML = rules.REFILLED_AT_ML
_done_key = rules.done_key


class UnknownItem(LookupError):
    """No maintenance item of that name in the settings."""


class CareMeter:
    """Wear totals, the maintenance schedule, pot life and glue level (see the module doc)."""

    def __init__(
        self,
        settings: Callable[[], MaintenanceSettings],
        devices: CellDevices,
        journal: Journal,
        alerts: Alerts,
        clock: Clock,
    ) -> None:
        self._settings = settings  # read at each use: PATCH /settings may change them
        self.devices = devices
        self.journal = journal
        self.alerts = alerts
        self.clock = clock
        self.values: dict[str, float] = {name: 0.0 for name in COUNTERS}
        self._seen: dict[str, float] = {}  # the drivers' counters at the last read
        # A copy of each device's details (glue, robot, camera) at the last read; None
        # before the first.
        self._details: list[dict[str, Any] | None] = [None, None, None]
        self._raised: dict[str, str] = {}  # each condition warned of, until it ends: its code
        self._timer: Timer | None = None
        self._persisted_at = 0.0
        self._written: dict[str, float] = {}  # each key's value as the journal has it
        self._planned_items: tuple[MaintenanceItem, ...] | None = None  # see _plans
        self._item_plans: tuple[tuple[MaintenanceItem, rules.ItemPlan, str, str], ...] = ()
        # The statuses `_statuses` last judged, with the plans, percent and totals they
        # were judged from.
        self._judged: (
            tuple[
                tuple[tuple[MaintenanceItem, rules.ItemPlan, str, str], ...],
                float,
                dict[str, float],
                tuple[str, ...],
            ]
            | None
        ) = None

    # --- lifecycle -------------------------------------------------------------

    def load(self, path: Path) -> None:
        """The totals and marks as the journal last kept them."""
        kept = wear_table.read(path)
        self.values.update(kept)
        self._written = dict(kept)

    def start(self) -> None:
        self._persisted_at = self.clock.monotonic()
        self._schedule()

    def stop(self) -> None:
        """Stop checking; the totals are written a last time."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self.read_drivers()
        self.persist(every_key=True)

    def _schedule(self) -> None:
        self._timer = self.clock.call_later(self._settings().care_check_interval, self._tick)

    def _tick(self) -> None:
        try:
            self.check()
            if (
                self.clock.monotonic() - self._persisted_at
                >= self._settings().wear_persist_interval
            ):
                self.persist(every_key=True)
        except Exception:  # a check must never stop the checks
            log.exception("the wear and maintenance check failed")
        finally:
            self._schedule()

    # --- counting --------------------------------------------------------------

    def read_drivers(self) -> None:
        """Add what each driver's counters grew by since the last read.

        Every check and every run's end reads them, so a device whose details are
        those of the last read (one comparison of two dicts) is passed over: none of
        its counters grew. The others' counters are read in FROM_DRIVERS' order."""
        devices, seen, values, last = self.devices, self._seen, self.values, self._details
        dispensed = False
        for at, device, counters in (
            (0, devices.glue, _GLUE_COUNTERS),
            (1, devices.robot, _ROBOT_COUNTERS),
            (2, devices.camera, _CAMERA_COUNTERS),
        ):
            details = device.health.details
            if details == last[at]:
                continue
            last[at] = dict(details)
            for name, key in counters:
                now = float(details.get(key, 0.0))
                grew = now - seen.get(name, 0.0)
                seen[name] = now
                if grew > 0:
                    values[name] = values.get(name, 0.0) + grew
                    dispensed = dispensed or name in ("valve_cycles", "glue_ml")
        if dispensed:
            self.note_dispense()

    def note_dispense(self) -> None:
        """Glue just flowed: the pot life starts again (its warnings clear at the check)."""
        self.values[LAST_DISPENSE] = self.clock.time()

    def run_ended(self, ended: RunEnded) -> None:
        """A run's parts counted and everything written (a run listener)."""
        if ended.operation == "trajectory" and ended.outcome == "completed":
            self.values["parts"] = self.values.get("parts", 0.0) + ended.workpieces
        self.check()
        self.persist()

    def purged(self) -> None:
        """A purge ended (the valve closed after it had opened)."""
        self.values["purges"] = self.values.get("purges", 0.0) + 1
        self.read_drivers()
        self.note_dispense()
        self.check()
        self.persist()

    def persist(self, *, every_key: bool = False) -> None:
        """The totals and marks to the journal, not awaited (durable=False): a row per
        key, only the keys changed since they were last written (a run's end writes the
        few it changed), or `every_key` (the periodic write and the last one at stop,
        which also make good a write the journal could not take)."""
        self._persisted_at = self.clock.monotonic()
        if not every_key and self.values == self._written:  # nothing changed (one C compare)
            return
        changed = {k: v for k, v in self.values.items() if every_key or self._written.get(k) != v}
        if changed:
            self.journal.append(wear_table.records(changed, self.clock.time()), durable=False)
            self._written.update(changed)

    # --- what people do --------------------------------------------------------

    def done(self, name: str) -> dict[str, Any]:
        """Restart an item's intervals from the totals now; its state after."""
        item = self.item(name)
        self.read_drivers()
        for counter in item.intervals():
            self.values[_done_key(item.name, counter)] = self.values.get(counter, 0.0)
        self.values[f"done_at:{item.name}"] = self.clock.time()
        self.check()  # its warnings clear
        self.persist()
        return self._item_state(item)

    def refill(self) -> dict[str, Any]:
        """The reservoir was filled: the level is full from the glue dispensed now."""
        self.read_drivers()
        self.values[REFILLED_AT_ML] = self.values.get("glue_ml", 0.0)
        self.check()  # the low-level warning clears
        self.persist()
        return self.glue_level()

    def item(self, name: str) -> MaintenanceItem:
        for item in self._settings().maintenance_items:
            if item.name.lower() == name.strip().lower():
                return item
        raise UnknownItem(name)

    # --- judging ---------------------------------------------------------------

    def check(self) -> None:
        """Read the drivers, raise each warning whose condition has just begun, and clear
        each whose condition has ended.

        Run at every run's end as well as on the timer, so it judges by the statuses
        alone (`care_rules.item_status`, `pot_status`, `glue_status`) and builds a
        warning's message only when the warning is raised."""
        self.read_drivers()
        settings, values, now = self._settings(), self.values, self.clock.time()
        holding: set[str] = set()
        items = settings.maintenance_items
        plans = self._item_plans if items is self._planned_items else self._plans(items)
        statuses = self._statuses(plans, values, settings)
        for (item, plan, due, overdue), status in zip(plans, statuses, strict=True):
            if status == "overdue":
                code = "MAINTENANCE_OVERDUE"
                self._raise_once(overdue, code, item, plan)
                holding.add(overdue)
                if due in self._raised:  # still due, as it was
                    holding.add(due)
            elif status == "due":
                code = "MAINTENANCE_DUE"
                self._raise_once(due, code, item, plan)
                holding.add(due)
        pot = rules.pot_status(values, settings, now)
        if pot == "expired":
            code = "POT_LIFE_EXCEEDED"
            self._warn_once(code, lambda: rules.pot_life(values, settings, now), "glue")
            holding.add(code)
            if "POT_LIFE_NEAR" in self._raised:
                holding.add("POT_LIFE_NEAR")
        elif pot == "near":
            code = "POT_LIFE_NEAR"
            self._warn_once(code, lambda: rules.pot_life(values, settings, now), "glue")
            holding.add(code)
        if rules.glue_status(values, settings) == "low":
            code = "GLUE_LEVEL_LOW"
            self._warn_once(code, lambda: rules.glue_level(values, settings), "glue")
            holding.add(code)
        if len(holding) != len(self._raised):  # every warning raised holds: none to clear
            self._clear_ended(holding)

    def _statuses(
        self,
        plans: tuple[tuple[MaintenanceItem, rules.ItemPlan, str, str], ...],
        values: dict[str, float],
        settings: MaintenanceSettings,
    ) -> tuple[str, ...]:
        """Each planned item's status (`care_rules.item_status`), the last ones again while
        the plans, the totals and maintenance_overdue_percent are those they were judged
        from: the status reads nothing else, and between two runs' ends the totals are
        often the same, which one comparison of the two dicts finds."""
        percent = settings.maintenance_overdue_percent
        judged = self._judged
        if (
            judged is not None
            and judged[0] is plans
            and judged[1] == percent
            and judged[2] == values
        ):
            return judged[3]
        statuses = tuple(rules.item_status(plan, values, settings) for _, plan, _, _ in plans)
        self._judged = (plans, percent, dict(values), statuses)
        return statuses

    def _plans(
        self, items: tuple[MaintenanceItem, ...]
    ) -> tuple[tuple[MaintenanceItem, rules.ItemPlan, str, str], ...]:
        """Each item with its plan and the keys of its due and overdue warnings, worked
        out again only when the schedule is another (PATCH /settings replaces it: `check`
        keeps them while it is the same)."""
        self._planned_items = items
        self._item_plans = tuple(
            (item, rules.item_plan(item), f"due:{item.name}", f"overdue:{item.name}")
            for item in items
        )
        return self._item_plans

    def _raise_once(self, key: str, code: str, item: MaintenanceItem, plan: rules.ItemPlan) -> None:
        if key not in self._raised:
            self._raised[key] = code
            state = rules.item_state(item, self.values, self._settings(), plan)
            message = (
                f"maintenance {state['status']}: {state['name']} ({state['reason']}); "
                f"when done, POST /maintenance/{state['name']}/done"
            )
            self.alerts.warn(code, message, "maintenance", standing=True)

    def _warn_once(self, code: str, judged: Callable[[], dict[str, Any]], component: str) -> None:
        if code not in self._raised:
            self._raised[code] = code
            self.alerts.warn(code, judged()["message"], component, standing=True)

    def _clear_ended(self, holding: set[str]) -> None:
        """Forget the warnings whose condition no longer holds; a code none still holds
        is cleared on every channel."""
        ended = {key: code for key, code in self._raised.items() if key not in holding}
        for key in ended:
            del self._raised[key]
        for code in sorted(set(ended.values()) - set(self._raised.values())):
            keys = sorted(key for key, of in ended.items() if of == code)
            self.alerts.cleared(code, _why_over(code, keys), _component_of(code))

    def _item_state(self, item: MaintenanceItem) -> dict[str, Any]:
        return rules.item_state(item, self.values, self._settings())

    def pot_life(self) -> dict[str, Any]:
        """The open time since the last dispense against the adhesive's pot life."""
        return rules.pot_life(self.values, self._settings(), self.clock.time())

    def start_problem(self) -> str | None:
        """Why a start must wait for a purge (pot life past), or None (asked at every start)."""
        settings, now = self._settings(), self.clock.time()
        if rules.pot_status(self.values, settings, now) != "expired":
            return None
        message: str = rules.pot_life(self.values, settings, now)["message"]
        return message

    def glue_level(self) -> dict[str, Any]:
        """The reservoir's estimated level from the glue dispensed since the last refill."""
        return rules.glue_level(self.values, self._settings())

    def state(self) -> dict[str, Any]:
        """What GET /maintenance shows."""
        self.read_drivers()
        return rules.state_of(self.values, self._settings(), self.clock.time())


def _component_of(code: str) -> str:
    return "maintenance" if code.startswith("MAINTENANCE_") else "glue"


def _why_over(code: str, keys: list[str]) -> str:
    """What a cleared warning's message says ended it."""
    if code.startswith("MAINTENANCE_"):
        items = ", ".join(key.split(":", 1)[1] for key in keys)
        return f"maintenance no longer {code.removeprefix('MAINTENANCE_').lower()}: {items}"
    if code.startswith("POT_LIFE_"):
        return "glue dispensed since (a run or a purge): the pot life starts again"
    return "the glue reservoir is above glue_low_level_percent again (refilled)"
