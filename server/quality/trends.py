"""Control charts of each part's quality figures, and the drift rule that warns before a
part goes out of tolerance.

Why: a nozzle that clogs, a valve that wears or a camera that shifts moves a figure a
little with every part long before one part is defective. Each figure of the inspected
parts is charted in order against a centre line and limits taken from the last
`trend_baseline_parts` good parts before the latest `trend_run_length` points (so the
points being judged never move their own centre). The drift rule is two of the Western
Electric rules: the latest point beyond `trend_sigma` standard deviations, or the latest
`trend_run_length` points all on one side of the centre line. It names the figure, the
way it moves, and what to check.

The spread is never taken below 1 % of the centre (nor below 1e-9): a figure the
instruments round, on a cell as steady as the simulator, must not warn on its last digit.

Pure: no I/O, no clock.
"""

from __future__ import annotations

import statistics
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Final

from server.quality.part_verdict import figure_of
from server.settings.watch import WatchSettings

LEAST_SPREAD_SHARE: Final = 0.01
LEAST_SPREAD: Final = 1e-9


@dataclass(frozen=True)
class Figure:
    """One charted figure: its key in the summary, how it reads, and what to check."""

    name: str
    label: str
    unit: str
    check_high: str
    check_low: str


FIGURES: Final = (
    Figure(
        "bead_width_percent",
        "bead width",
        "% of expected",
        "the flow and the pressure setpoint, and whether the robot slowed",
        "the nozzle for a clog, the glue supply and the flow",
    ),
    Figure(
        "glue_volume_percent",
        "glue volume",
        "% of expected",
        "the flow setpoint, the pressure and the valve's closing",
        "the nozzle for a clog, the glue supply and the valve",
    ),
    Figure(
        "dispensing_cv_percent",
        "dispensing CV",
        "%",
        "the nozzle, air in the glue line and the pressure regulator",
        "nothing urgent: the flow is steadier than usual",
    ),
    Figure(
        "precision_p95_mm",
        "path precision (p95)",
        "mm",
        "the robot's speed, payload and mounting, and the robot calibration",
        "nothing urgent: the robot tracks its path better than usual",
    ),
    Figure(
        "vision_residual_mm",
        "vision residual",
        "mm",
        "the camera's mount, focus and the table; run calibrate-robot",
        "nothing urgent: the markers sit closer than usual",
    ),
)
FIGURE_NAMES: Final = tuple(figure.name for figure in FIGURES)


def bead_width_percent(document: Mapping[str, Any]) -> float | None:
    """The bead's mean width as a percentage of the width its segments expect (their mean):
    comparable across workpieces and speeds, as the width itself is not."""
    ratios = []
    for segment in document.get("segments") or []:
        width = segment.get("width_mean_mm")
        expected = segment.get("expected_width_mm")
        if isinstance(width, int | float) and isinstance(expected, int | float) and expected > 0:
            ratios.append(100.0 * width / expected)
    return round(statistics.fmean(ratios), 2) if ratios else None


def glue_volume_percent(document: Mapping[str, Any]) -> float | None:
    """The glue dispensed as a percentage of what the path needs."""
    dispensing = document.get("dispensing") or {}
    value = dispensing.get("glue_ratio_percent")
    return float(value) if isinstance(value, int | float) else None


def figures_of_document(document: Mapping[str, Any]) -> dict[str, float | None]:
    """Every charted figure of a whole inspection (the journal's `inspections` row)."""
    precision = document.get("precision") or {}
    dispensing = document.get("dispensing") or {}
    vision = document.get("vision") or {}
    summary = {
        "bead_width_percent": bead_width_percent(document),
        "glue_volume_percent": glue_volume_percent(document),
        "dispensing_cv_percent": dispensing.get("cv_percent"),
        "precision_p95_mm": precision.get("p95_mm"),
        "vision_residual_mm": vision.get("residual_mean_mm"),
    }
    return figures_of_summary(summary)


def figures_of_summary(summary: Mapping[str, Any]) -> dict[str, float | None]:
    """Every charted figure of a run result's inspection summary."""
    return {name: figure_of(summary, name) for name in FIGURE_NAMES}


@dataclass(frozen=True)
class Point:
    """One inspected part on the charts."""

    run_id: str
    at: float
    good: bool
    figures: Mapping[str, float | None]


@dataclass(frozen=True)
class Limits:
    centre: float
    sigma: float
    lower: float
    upper: float
    parts: int  # the good parts they were taken from


@dataclass(frozen=True)
class Drift:
    """A figure drifting: which, which way, why, and what to check."""

    figure: Figure
    direction: str  # "up" or "down"
    rule: str
    limits: Limits

    @property
    def code(self) -> str:
        return f"QUALITY_DRIFT_{self.figure.name.upper()}"

    def message(self, run_id: str) -> str:
        f, lim = self.figure, self.limits
        check = f.check_high if self.direction == "up" else f.check_low
        return (
            f"{f.label} is drifting {self.direction} ({self.rule}, part of run {run_id}); its "
            f"centre line is {lim.centre:.3g} {f.unit}, limits {lim.lower:.3g} to "
            f"{lim.upper:.3g} from the last {lim.parts} good parts: check {check} before "
            "parts go out of tolerance"
        )


def limits_of(points: Sequence[Point], name: str, settings: WatchSettings) -> Limits | None:
    """The chart's centre and limits: the last `trend_baseline_parts` good parts before the
    latest `trend_run_length` points; None with fewer than `trend_min_parts` of them."""
    earlier = points[: max(0, len(points) - settings.trend_run_length)]
    values = [
        value for point in earlier if point.good and (value := point.figures.get(name)) is not None
    ][-settings.trend_baseline_parts :]
    if len(values) < max(settings.trend_min_parts, 2):
        return None
    centre = statistics.fmean(values)
    sigma = max(statistics.stdev(values), abs(centre) * LEAST_SPREAD_SHARE, LEAST_SPREAD)
    reach = settings.trend_sigma * sigma
    return Limits(centre, sigma, centre - reach, centre + reach, len(values))


def drift_of(points: Sequence[Point], figure: Figure, settings: WatchSettings) -> Drift | None:
    """Whether the latest point of `figure` breaks the drift rule (module docstring)."""
    if not points or points[-1].figures.get(figure.name) is None:
        return None
    limits = limits_of(points, figure.name, settings)
    if limits is None:
        return None
    latest = points[-1].figures[figure.name]
    assert latest is not None
    if not limits.lower <= latest <= limits.upper:
        direction = "up" if latest > limits.upper else "down"
        rule = f"{latest:.3g} {figure.unit} is beyond {settings.trend_sigma:g} sigma"
        return Drift(figure, direction, rule, limits)
    run = settings.trend_run_length
    recent = [point.figures.get(figure.name) for point in points[-run:]]
    if len(recent) < run or any(value is None for value in recent):
        return None
    if all(value is not None and value > limits.centre for value in recent):
        return Drift(figure, "up", f"{run} parts in a row above the centre line", limits)
    if all(value is not None and value < limits.centre for value in recent):
        return Drift(figure, "down", f"{run} parts in a row below the centre line", limits)
    return None


def charts(points: Sequence[Point], settings: WatchSettings) -> list[dict[str, Any]]:
    """Every figure's chart as GET /quality/trends gives it: its series and its limits."""
    result = []
    for figure in FIGURES:
        limits = limits_of(points, figure.name, settings)
        drift = drift_of(points, figure, settings)
        result.append(
            {
                "figure": figure.name,
                "label": figure.label,
                "unit": figure.unit,
                "centre": None if limits is None else round(limits.centre, 4),
                "sigma": None if limits is None else round(limits.sigma, 4),
                "lower": None if limits is None else round(limits.lower, 4),
                "upper": None if limits is None else round(limits.upper, 4),
                "baseline_parts": 0 if limits is None else limits.parts,
                "drift": None
                if drift is None
                else {"direction": drift.direction, "rule": drift.rule},
                "points": [
                    {
                        "run_id": point.run_id,
                        "at": point.at,
                        "good": point.good,
                        "value": point.figures.get(figure.name),
                    }
                    for point in points
                    if point.figures.get(figure.name) is not None
                ],
            }
        )
    return result
