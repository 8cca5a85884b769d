"""The watch's rules, pure: when a figure is worth a warning, and when it is said once.

Each rule answers for one sample; `Latch` turns a condition that holds for many samples
into one warning when it starts (and again only after it has cleared), so a cell short
of memory for an hour says so once, not every few seconds.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass


class Latch:
    """True on the sample a condition starts holding; False while it goes on or is clear."""

    def __init__(self) -> None:
        self.on = False

    def rises(self, holds: bool) -> bool:
        rose = holds and not self.on
        self.on = holds
        return rose


def memory_level(used: int, limit: int, warning_percent: float) -> str:
    """'ok', 'warning' (at warning_percent of the limit or more) or 'alert' (at the limit)."""
    if used >= limit:
        return "alert"
    if used * 100 >= limit * warning_percent:
        return "warning"
    return "ok"


def percentile(values: Sequence[float], share: float) -> float:
    """The nearest-rank percentile of `values` (share 0-1): a figure that was measured."""
    ordered = sorted(values)
    rank = max(1, math.ceil(share * len(ordered)))
    return ordered[rank - 1]


@dataclass(frozen=True)
class RttFigures:
    """A device's round trips: the latest window's p95 against the baseline window's."""

    p95_ms: float | None
    baseline_p95_ms: float | None
    samples: int

    def as_dict(self) -> dict[str, float | int | None]:
        return {
            "p95_ms": self.p95_ms,
            "baseline_p95_ms": self.baseline_p95_ms,
            "samples": self.samples,
        }


class RttTrend:
    """One device's round trips: the first full window is its baseline; the latest window
    degrades when its p95 is `factor` times the baseline's and `min_rise_ms` over it."""

    def __init__(self, window: int, factor: float, min_rise_ms: float) -> None:
        self.window = window
        self.factor = factor
        self.min_rise_ms = min_rise_ms
        self.recent: deque[float] = deque(maxlen=window)
        self.baseline: float | None = None
        self.latch = Latch()

    def add(self, rtt_ms: float) -> bool:
        """Take one round trip; True when the link has just started to degrade."""
        self.recent.append(rtt_ms)
        if len(self.recent) < self.window:
            return False
        p95 = percentile(self.recent, 0.95)
        if self.baseline is None:
            self.baseline = p95
            return False
        return self.latch.rises(self.degraded(p95))

    def degraded(self, p95: float) -> bool:
        assert self.baseline is not None
        return p95 >= self.baseline * self.factor and p95 - self.baseline >= self.min_rise_ms

    def figures(self) -> RttFigures:
        p95 = percentile(self.recent, 0.95) if self.recent else None
        return RttFigures(p95, self.baseline, len(self.recent))


class ErrorRate:
    """Failed operations per 100 among the latest `window` that ended; judged once the
    window is full, so the first failure of a shift is not a rate of 100 %."""

    def __init__(self, window: int, alert_per_100: float) -> None:
        self.outcomes: deque[bool] = deque(maxlen=window)
        self.alert_per_100 = alert_per_100
        self.latch = Latch()

    def add(self, failed: bool) -> bool:
        """Take one ended operation; True when the rate has just risen over the limit."""
        self.outcomes.append(failed)
        rate = self.per_100()
        full = len(self.outcomes) == self.outcomes.maxlen
        return self.latch.rises(full and rate is not None and rate > self.alert_per_100)

    def per_100(self) -> float | None:
        if not self.outcomes:
            return None
        return 100.0 * sum(self.outcomes) / len(self.outcomes)

    def extend(self, failures: Iterable[bool]) -> None:
        """The history, before the cell started: counted, never alerted on."""
        for failed in failures:
            self.outcomes.append(failed)
        rate = self.per_100()
        self.latch.on = (
            len(self.outcomes) == self.outcomes.maxlen
            and rate is not None
            and rate > self.alert_per_100
        )
