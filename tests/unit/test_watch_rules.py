"""The self-watch's rules on their own: a condition said once as it starts, the memory
levels, a link's round trips degrading against its baseline, the error rate's alert,
and the control charts' drift rule (server/watch/rules.py, server/quality/trends.py)."""

from __future__ import annotations

import random

from server.quality.trends import FIGURES, Point, charts, drift_of, limits_of
from server.settings.watch import WatchSettings
from server.watch.rules import ErrorRate, Latch, RttTrend, memory_level, percentile
from server.watch.system import process_use, unique_bytes

SETTINGS = WatchSettings()
GLUE = next(figure for figure in FIGURES if figure.name == "glue_volume_percent")


def test_a_latch_says_a_condition_once_until_it_clears() -> None:
    latch = Latch()
    assert [latch.rises(h) for h in (False, True, True, False, True)] == [
        False, True, False, False, True,
    ]  # fmt: skip


def test_memory_levels() -> None:
    limit = 500 * 1024**2
    assert memory_level(limit // 2, limit, 80) == "ok"
    assert memory_level(limit * 4 // 5 - 1, limit, 80) == "ok"
    assert memory_level(limit * 4 // 5, limit, 80) == "warning"
    assert memory_level(limit, limit, 80) == "alert"


def test_a_link_degrades_against_its_first_window_not_for_jitter() -> None:
    trend = RttTrend(window=10, factor=3, min_rise_ms=20)
    steady = [1.0 + 0.1 * (i % 3) for i in range(10)]
    assert not any(trend.add(rtt) for rtt in steady)  # the baseline
    assert trend.baseline == percentile(steady, 0.95)
    assert not any(trend.add(rtt * 5) for rtt in steady)  # 5 times, but 6 ms: jitter
    raised = [trend.add(40.0) for _ in range(10)]
    assert raised.count(True) == 1  # once, as the window's p95 passes the rule
    assert not trend.add(40.0)


def test_the_error_rate_alerts_once_the_window_is_full_and_over_the_limit() -> None:
    rate = ErrorRate(window=10, alert_per_100=10)
    assert not rate.add(True)  # the first failure alone is no rate: the window is not full
    assert not any(rate.add(False) for _ in range(9))  # full: 1 in 10 is not over 10
    assert not rate.add(True)  # the failure dropped from the window: still 1 in 10
    assert rate.add(True)  # 2 in 10
    assert not rate.add(True)  # said once
    assert rate.per_100() == 30.0  # 3 in 10


def test_history_is_counted_without_an_alert() -> None:
    rate = ErrorRate(window=4, alert_per_100=10)
    rate.extend([True, True, False, False])
    assert rate.latch.on and not rate.add(True)


def test_the_process_figures_of_this_process() -> None:
    import os

    use = process_use(os.getpid())
    assert use.resident_bytes and use.unique_bytes and use.threads and use.open_files
    assert use.unique_bytes <= use.resident_bytes
    assert use.cpu_seconds is not None and use.cpu_seconds > 0
    assert unique_bytes(2**22 + 12345) is None  # no such process: None, no error


def part(index: int, glue: float, *, good: bool = True) -> Point:
    return Point(f"run-{index}", float(index), good, {"glue_volume_percent": glue})


def steady(count: int, seed: int = 1) -> list[Point]:
    noise = random.Random(seed)
    return [part(i, 100 + noise.gauss(0, 1.5)) for i in range(count)]


def test_a_steady_figure_is_seldom_called_a_drift() -> None:
    """On a steady cell the rule still fires by chance (a run on one side happens); with
    the defaults, warnings (each said once, as in the watch) stay under one per 50 parts."""
    points = steady(2000)
    latch = Latch()
    warned = sum(
        latch.rises(drift_of(points[max(0, i - 60) : i + 1], GLUE, SETTINGS) is not None)
        for i in range(len(points))
    )
    assert warned < len(points) / 50


def test_a_chart_is_not_judged_before_enough_good_parts() -> None:
    points = [part(i, 100 + i) for i in range(SETTINGS.trend_min_parts)]
    assert limits_of(points, GLUE.name, SETTINGS) is None and not drift_of(points, GLUE, SETTINGS)


def test_one_part_beyond_three_sigma_is_a_drift() -> None:
    points = [*steady(30), part(30, 80.0)]
    drift = drift_of(points, GLUE, SETTINGS)
    assert drift is not None and drift.direction == "down" and "beyond 3 sigma" in drift.rule
    assert drift.code == "QUALITY_DRIFT_GLUE_VOLUME_PERCENT"
    assert "check the nozzle for a clog" in drift.message("run-30")


def test_a_run_of_parts_on_one_side_are_a_drift_within_the_limits() -> None:
    points = steady(30)
    limits = limits_of(points, GLUE.name, SETTINGS)
    assert limits is not None
    points.append(part(30, limits.centre - limits.sigma))  # the last below the centre
    run = SETTINGS.trend_run_length
    above = [part(31 + i, limits.centre + limits.sigma) for i in range(run)]
    assert not drift_of([*points, *above[:-1]], GLUE, SETTINGS)
    drift = drift_of([*points, *above], GLUE, SETTINGS)
    assert drift is not None and drift.direction == "up"
    assert drift.rule == f"{run} parts in a row above the centre line"


def test_the_limits_come_from_good_parts_only() -> None:
    points = [*steady(20), part(20, 10.0, good=False), *steady(10, seed=2)]
    limits = limits_of(points, GLUE.name, SETTINGS)
    assert limits is not None and limits.lower > 90


def test_charts_give_every_figure_its_series_and_limits() -> None:
    by_name = {chart["figure"]: chart for chart in charts(steady(30), SETTINGS)}
    assert set(by_name) == {figure.name for figure in FIGURES}
    glue = by_name["glue_volume_percent"]
    assert len(glue["points"]) == 30 and glue["lower"] < glue["centre"] < glue["upper"]
    assert glue["drift"] is None
    assert by_name["precision_p95_mm"]["points"] == []  # not measured: no series
