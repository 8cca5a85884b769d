"""What one status read of the glue dispenser shows: the onsets it reports, the faults it shows.

`StatusWatch.observe` judges each reading (the monitor's polls and every other
status read) and reports each excursion once per onset, not on every poll:

* "ALARM": each new alarm bit of the dispenser's own;
* "PRESSURE_OUT_OF_RANGE": above the high end of `pressure_range_psi` at any
  time (over-pressure is a hazard whatever the valve does), below its low end
  while the valve reads open, on every poll for `flow_deviation_s` (a sagging
  supply sprays thin; a supply at rest between runs is no fault, and a reset
  probes with the valve closed);
* "FLOW_DEVIATION": while the valve reads open, measured flow off its setpoint
  by more than `flow_tolerance_pct` % on every poll for `flow_deviation_s`
  (the valve's opening transient is shorter, a blocked or starved nozzle not);
* "TEMPERATURE_OUT_OF_RANGE": outside `temperature_range_c`, at any time.

An excursion is news again once the reading came back inside with a margin
(the hysteresis below), or after `reset` (a new connection).
"""

from __future__ import annotations

import time
from collections.abc import Callable

from server.drivers.base import GlueStatus

PRESSURE_HYSTERESIS_PSI = 1.0
TEMPERATURE_HYSTERESIS_C = 0.5

Report = Callable[[str, str], None]  # (fault code, message)


class StatusWatch:
    """The supervision of the dispenser's readings; `None` limits switch a check off."""

    def __init__(
        self,
        report: Report,
        *,
        pressure_range_psi: tuple[float, float],
        flow_tolerance_pct: float | None,
        flow_deviation_s: float,
        temperature_range_c: tuple[float, float] | None,
    ) -> None:
        self._report = report
        self.pressure_range_psi = pressure_range_psi
        self.flow_tolerance_pct = flow_tolerance_pct
        self.flow_deviation_s = flow_deviation_s
        self.temperature_range_c = temperature_range_c
        self.reset()

    def reset(self) -> None:
        """Forget every excursion: alarms and excursions still present are news again."""
        self._active_alarms: frozenset[str] = frozenset()
        self._pressure_fault: str | None = None  # the excursion reported: high or low
        self._flow_fault = False
        self._flow_off_since: float | None = None  # monotonic time of the first deviating poll
        self._pressure_low_since: float | None = None  # the same, for pressure while spraying
        self._temperature_fault = False

    def valve_opening(self) -> None:
        """Each opening has its transient: the flow and the low pressure are judged from
        this opening on, never summed over short openings a poll did not see closed (a
        pause and a resume between two polls)."""
        self._flow_off_since = None
        self._pressure_low_since = None

    def observe(self, status: GlueStatus) -> tuple[str, ...]:
        """Report the onsets `status` shows; the faults active now, for the health."""
        new = [name for name in status.alarms if name not in self._active_alarms]
        self._active_alarms = frozenset(status.alarms)
        if new:
            self._report(
                "ALARM",
                f"glue dispenser alarm: {', '.join(new)} (pressure {status.pressure_psi:g} PSI, "
                f"flow {status.flow_ml_min:g} ml/min, {status.temperature_c:g} °C)",
            )
        faults = [f"glue: alarm {', '.join(status.alarms)}"] if status.alarms else []
        faults += self._pressure(status)
        faults += self._flow(status)
        faults += self._temperature(status)
        return tuple(faults)

    def _pressure(self, status: GlueStatus) -> list[str]:
        """The high limit always; the low one while the valve reads open, for flow_deviation_s.

        A valve opening draws the supply down for a moment (and the first setpoint
        of a run is still rising): the same grace as a flow deviation's.
        """
        low, high = self.pressure_range_psi
        low_applies = status.valve_open and low > 0
        pressure = status.pressure_psi
        sagging = False
        if low_applies and pressure < low:
            now = time.monotonic()
            if self._pressure_low_since is None:
                self._pressure_low_since = now
            sagging = now - self._pressure_low_since >= self.flow_deviation_s
        else:
            self._pressure_low_since = None
        kind = "high" if pressure > high else "low" if sagging else None
        if kind is not None:
            if kind != self._pressure_fault:  # a new excursion (or the other side): news
                self._pressure_fault = kind
                while_open = " while spraying" if kind == "low" else ""
                self._report(
                    "PRESSURE_OUT_OF_RANGE",
                    f"glue pressure {pressure:g} PSI is outside the allowed {low:g}-{high:g} PSI"
                    f"{while_open} (setpoint {status.pressure_setpoint_psi:g} PSI)",
                )
            return [f"glue: pressure {pressure:.1f} PSI outside {low:g}..{high:g} PSI"]
        if self._pressure_fault is not None:
            margin_low = low + PRESSURE_HYSTERESIS_PSI if low_applies else 0.0
            if margin_low <= pressure <= high - PRESSURE_HYSTERESIS_PSI:
                self._pressure_fault = None  # back inside with margin: the next excursion reports
        return []

    def _flow(self, status: GlueStatus) -> list[str]:
        """Measured flow off its setpoint while the valve reads open, for flow_deviation_s."""
        tolerance = self.flow_tolerance_pct
        setpoint = status.flow_setpoint_ml_min
        if tolerance is None or not status.valve_open or setpoint <= 0:
            self._flow_off_since = None
            self._flow_fault = False
            return []
        deviation_pct = abs(status.flow_ml_min - setpoint) / setpoint * 100.0
        if deviation_pct <= tolerance:
            self._flow_off_since = None
            self._flow_fault = False
            return []
        now = time.monotonic()
        if self._flow_off_since is None:
            self._flow_off_since = now
        if now - self._flow_off_since < self.flow_deviation_s:
            return []  # the valve's opening transient, or a setpoint change settling
        if not self._flow_fault:
            self._flow_fault = True
            self._report(
                "FLOW_DEVIATION",
                f"glue flow {status.flow_ml_min:g} ml/min is {deviation_pct:.0f} % off its "
                f"setpoint {setpoint:g} ml/min (allowed {tolerance:g} %) for "
                f"{self.flow_deviation_s:g} s while spraying; check the nozzle and the supply",
            )
        return [f"glue: flow {status.flow_ml_min:.1f} ml/min, {deviation_pct:.0f} % off setpoint"]

    def _temperature(self, status: GlueStatus) -> list[str]:
        if self.temperature_range_c is None:
            return []
        low, high = self.temperature_range_c
        temperature = status.temperature_c
        if not low <= temperature <= high:
            if not self._temperature_fault:
                self._temperature_fault = True
                self._report(
                    "TEMPERATURE_OUT_OF_RANGE",
                    f"glue temperature {temperature:g} °C is outside the allowed "
                    f"{low:g}-{high:g} °C",
                )
            return [f"glue: temperature {temperature:.1f} °C outside {low:g}..{high:g} °C"]
        if self._temperature_fault and (
            low + TEMPERATURE_HYSTERESIS_C <= temperature <= high - TEMPERATURE_HYSTERESIS_C
        ):
            self._temperature_fault = False
        return []
