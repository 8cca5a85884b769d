"""What the soak measures at its start (after the warm-up) and at its end: the
process's memory and open files, the journal's size on disk, and how long the
soak's own clients waited for their answers.

Why these: a leak that costs one file descriptor per WebSocket client or a few
kilobytes per command does not fail any single test, and shows only over
thousands of them. Open descriptors are judged (they must come back to where
they were, within `FD_SLACK`); memory, the journal's size and the latencies are
reported, because each also grows or drifts for reasons that are no fault
(caches warming, the journal keeping its history, the machine's other work).

Everything runs in the soak's process (server, simulators, clients), so the
figures are that process's.
"""

from __future__ import annotations

import statistics
from array import array
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import psutil

# Descriptors the end may hold beyond the start: pooled keep-alive connections (both
# ends are in this process) and the journal's files come and go between two quiet
# moments. A leak of one per WebSocket client or per command exceeds it within minutes.
FD_SLACK = 32
WINDOW_SHARE = 0.2  # each latency window: this share of the run after the warm-up
KINDS = ("GET /state", "POST command")


def open_fds() -> int:
    return psutil.Process().num_fds()


def rss_mb() -> float:
    return psutil.Process().memory_info().rss / 2**20


def journal_mb(path: Path) -> float:
    """The journal's database and its write-ahead log, on disk."""
    files = (path, path.with_name(path.name + "-wal"))
    return sum(f.stat().st_size for f in files if f.exists()) / 2**20


@dataclass(frozen=True)
class Percentiles:
    count: int
    p50_ms: float
    p99_ms: float

    @classmethod
    def of(cls, seconds: array) -> Percentiles:
        if len(seconds) < 2:
            only = seconds[0] * 1000 if seconds else 0.0
            return cls(len(seconds), round(only, 2), round(only, 2))
        cuts = statistics.quantiles(seconds, n=100, method="inclusive")
        return cls(len(seconds), round(cuts[49] * 1000, 2), round(cuts[98] * 1000, 2))

    def __str__(self) -> str:
        return f"{self.p50_ms:.1f} / {self.p99_ms:.1f} ms (n {self.count})"


class Latencies:
    """Answer times in two windows: the first and the last `WINDOW_SHARE` of the run
    after the warm-up. Only those are kept (in arrays), so a run of hours holds a few
    hundred kilobytes of them rather than growing the memory it reports on."""

    def __init__(self) -> None:
        self._windows: tuple[tuple[float, float], tuple[float, float]] | None = None
        self._kept: dict[tuple[str, int], array] = {}

    def open_windows(self, warm_at: float, end_at: float) -> None:
        """Set the windows once the warm-up is over (times in time.monotonic())."""
        width = max(end_at - warm_at, 0.0) * WINDOW_SHARE
        self._windows = ((warm_at, warm_at + width), (end_at - width, float("inf")))

    def add(self, kind: str, at: float, seconds: float) -> None:
        if self._windows is None:
            return
        for index, (start, end) in enumerate(self._windows):
            if start <= at < end:
                self._kept.setdefault((kind, index), array("d")).append(seconds)

    def figures(self, window: int) -> dict[str, Percentiles]:
        """p50 and p99 of each kind in window 0 (start) or 1 (end)."""
        return {kind: Percentiles.of(self._kept.get((kind, window), array("d"))) for kind in KINDS}


@dataclass(frozen=True)
class Sample:
    """The soak's resources at one quiet moment: no WebSocket churn, no storm in flight."""

    at_s: float  # since the soak began
    rss_mb: float
    open_fds: int
    journal_mb: float
    websocket_clients: int  # as GET /health counts them

    @classmethod
    def take(cls, at_s: float, journal: Path, websocket_clients: int) -> Sample:
        return cls(
            round(at_s, 1),
            round(rss_mb(), 1),
            open_fds(),
            round(journal_mb(journal), 2),
            websocket_clients,
        )

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)
