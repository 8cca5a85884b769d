"""The cell watching itself while it runs, and saying so on every channel.

A task looks every `watch_interval_s` at the server's and the image process's CPU,
memory, open files and threads (system.py), the event loop's lag (loop_lag.py), the
data directory's free space and each device's round trip; each ended operation counts
in the error rate, and each inspected part goes on the quality control charts
(server/quality/trends.py). A condition worth a warning is raised through the cell's
`Alerts.warn` (the log, the journal's errors table as a warning, the WebSocket `alert`,
MQTT, OPC UA alarm events, webhooks), once as it starts (rules.py: `Latch`); the memory
and free-space warnings are cleared (`Alerts.cleared`) once their figure is back under
its threshold, so OPC UA's alarm condition goes inactive. Nothing here
acts on the cell: the memory limit is watched, never enforced (the cell runs on), and
no reading can fail the cell.

Its figures are read by GET /health (`system`), GET /metrics and GET /quality/trends.
Run listeners are told in the worker: they only keep the run, and judge it once the
worker has yielded (`call_soon`), never on its path.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from server.common.values import byte_size
from server.core.worker.runs import RunEnded
from server.quality.part_verdict import inspection_of
from server.quality.trends import (
    FIGURES,
    Point,
    charts,
    drift_of,
    figures_of_document,
    figures_of_summary,
)
from server.settings.watch import WatchSettings
from server.storage.journal import Journal
from server.vision.process import IMAGE_PROCESS
from server.watch.loop_lag import LoopLag
from server.watch.rules import ErrorRate, Latch, RttTrend, memory_level
from server.watch.system import DiskSpace, ProcessUse, disk_space, process_use

log = logging.getLogger(__name__)

MB = 1024**2
CHART_POINTS = 200  # parts kept on the charts (the baseline needs far fewer)


class Warn(Protocol):
    def __call__(
        self, code: str, message: str, component: str, *, severity: str = ..., standing: bool = ...
    ) -> None:
        """Raise a warning (or, with severity "alert", an alert) on every channel; a
        `standing` one holds until it is cleared."""


class Cleared(Protocol):
    def __call__(self, code: str, message: str, component: str) -> None:
        """Say a warning's cause has gone (an `alert_cleared` on every channel that keeps it)."""


@dataclass
class Sample:
    """The latest look: what GET /health's `system` block and /metrics show."""

    at: float
    server: ProcessUse
    image: ProcessUse | None
    cpu_percent: float | None
    memory_bytes: int | None
    memory_level: str
    loop_lag_s: float
    free_bytes: int | None
    total_bytes: int | None


class CellWatch:
    """Samples the cell's own figures, keeps its trends and raises what is worth raising."""

    def __init__(
        self,
        settings: Callable[[], WatchSettings],
        data_path: Path,
        device_health: Callable[[], dict[str, dict[str, Any]]],
        warn: Warn,
        journal: Journal | None = None,
        image_pids: Callable[[], list[int]] = IMAGE_PROCESS.pids,
        cleared: Cleared | None = None,
    ) -> None:
        self._settings = settings
        self._cleared = cleared
        self.data_path = data_path
        self._device_health = device_health
        self._warn = warn
        self._journal = journal
        self._image_pids = image_pids
        first = settings()
        self.loop_lag = LoopLag(first.loop_lag_interval_s)
        self.latest: Sample | None = None
        self._cpu_before: tuple[float, float] | None = None
        self._memory_level = "ok"
        self._memory_raised: set[str] = set()  # MEMORY_HIGH, MEMORY_LIMIT_REACHED until cleared
        self._disk = Latch()
        self.links: dict[str, RttTrend] = {}
        self.errors = ErrorRate(first.error_rate_window_operations, first.error_rate_alert_per_100)
        self.points: deque[Point] = deque(maxlen=CHART_POINTS)
        self._drifts = {figure.name: Latch() for figure in FIGURES}
        self._task: asyncio.Task[None] | None = None

    # --- life ------------------------------------------------------------------------------

    async def start(self) -> None:
        """Read the history (parts and outcomes) from the journal, then start looking."""
        if self._journal is not None:
            journal = self._journal
            inspections, outcomes = await asyncio.to_thread(self._history, journal)
            self._load(inspections, outcomes)
        self.loop_lag.start()
        self._judge(*await asyncio.to_thread(self._read))
        self._task = asyncio.create_task(self._every_interval(), name="cell-watch")

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        await self.loop_lag.stop()

    async def _every_interval(self) -> None:
        while True:
            await asyncio.sleep(self._settings().watch_interval_s)
            try:
                # The reads off the loop (a large process's smaps_rollup takes a while);
                # the judging on it, where the alerts are raised.
                self._judge(*await asyncio.to_thread(self._read))
            except Exception:  # a reading must never end the watch, nor the cell
                log.exception("the cell's self-watch could not take its figures")

    # --- the system ------------------------------------------------------------------------

    def look(self) -> Sample:
        """Take every figure once, and raise what has just started to hold."""
        return self._judge(*self._read())

    def _read(self) -> tuple[float, ProcessUse, ProcessUse | None, DiskSpace | None]:
        """The figures of /proc and the disk (any thread)."""
        pids = self._image_pids()
        return (
            time.monotonic(),
            process_use(os.getpid()),
            process_use(pids[0]) if pids else None,
            disk_space(self.data_path),
        )

    def _judge(
        self, now: float, server: ProcessUse, image: ProcessUse | None, disk: DiskSpace | None
    ) -> Sample:
        """The figures kept for /health and /metrics, and what they raise (on the loop)."""
        settings = self._settings()
        cpu = self._cpu_percent(now, server, image)
        # The server's own resident memory is what memory_limit bounds: the specification's
        # application is this process. The image process is shown beside it, not counted:
        # its memory is OpenCV and the frame buffers, sized by the camera, not by how long
        # the cell has run, so a leak shows in the server's figure.
        memory = server.resident_bytes
        level = self._judge_memory(memory, settings)
        self._judge_disk(disk.free_bytes if disk else None, settings)
        self._judge_links(settings)
        self.latest = Sample(
            at=time.time(),
            server=server,
            image=image,
            cpu_percent=cpu,
            memory_bytes=memory,
            memory_level=level,
            loop_lag_s=self.loop_lag.take_max(),
            free_bytes=disk.free_bytes if disk else None,
            total_bytes=disk.total_bytes if disk else None,
        )
        return self.latest

    def _cpu_percent(
        self, now: float, server: ProcessUse, image: ProcessUse | None
    ) -> float | None:
        """CPU of both processes since the last look, in percent of one core."""
        used = server.cpu_seconds
        if used is None:
            return None
        if image is not None and image.cpu_seconds is not None:
            used += image.cpu_seconds
        before, self._cpu_before = self._cpu_before, (now, used)
        if before is None or now <= before[0]:
            return None
        return round(max(0.0, 100.0 * (used - before[1]) / (now - before[0])), 1)

    def _clear(self, code: str, message: str, component: str) -> None:
        if self._cleared is not None:
            self._cleared(code, message, component)

    def _judge_memory(self, memory: int | None, settings: WatchSettings) -> str:
        if memory is None or settings.memory_limit is None:
            self._memory_level = "ok"
            self._clear_memory("ok", "memory_limit is not watched")
            return "ok"
        limit = byte_size(settings.memory_limit)
        level = memory_level(memory, limit, settings.memory_warning_percent)
        rank = {"ok": 0, "warning": 1, "alert": 2}
        if rank[level] > rank[self._memory_level]:
            used = f"{memory / MB:.0f} MB of memory_limit {settings.memory_limit}"
            if level == "alert":
                self._memory_raised.add("MEMORY_LIMIT_REACHED")
                self._warn(
                    "MEMORY_LIMIT_REACHED",
                    f"the server uses {used}: it runs on, "
                    "but a machine short of memory will slow and may end it; restart the "
                    "server in a pause and report it (glue-server diagnose)",
                    "system",
                    severity="alert",
                    standing=self._cleared is not None,
                )
            else:
                self._memory_raised.add("MEMORY_HIGH")
                self._warn(
                    "MEMORY_HIGH",
                    f"the server uses {used}, over {settings.memory_warning_percent:g} %: "
                    "watch it; restart the server in a pause if it keeps rising",
                    "system",
                    standing=self._cleared is not None,
                )
        self._memory_level = level
        self._clear_memory(level, f"the server uses {memory / MB:.0f} MB now")
        return level

    def _clear_memory(self, level: str, now: str) -> None:
        """The memory warnings whose threshold the server is back under, cleared."""
        ended = set()
        if level != "alert":
            ended.add("MEMORY_LIMIT_REACHED")
        if level == "ok":
            ended.add("MEMORY_HIGH")
        for code in sorted(ended & self._memory_raised):
            self._memory_raised.discard(code)
            self._clear(code, f"{now}: back under the threshold", "system")

    def _judge_disk(self, free: int | None, settings: WatchSettings) -> None:
        threshold = byte_size(settings.free_space_warning)
        if free is not None and self._disk.on and free >= threshold:
            self._clear(
                "DISK_SPACE_LOW",
                f"{free / MB:.0f} MB free on the disk of the data directory again "
                f"(free_space_warning {settings.free_space_warning})",
                "storage",
            )
        if free is not None and self._disk.rises(free < threshold):
            self._warn(
                "DISK_SPACE_LOW",
                f"{free / MB:.0f} MB free on the disk of the data directory {self.data_path} "
                f"(free_space_warning {settings.free_space_warning}): free space before the "
                "journal cannot write and commands are refused (delete old backups or logs, "
                "or lower analytics_retention_days)",
                "storage",
                standing=self._cleared is not None,
            )

    def _judge_links(self, settings: WatchSettings) -> None:
        for name, health in self._device_health().items():
            rtt = health.get("last_rtt_ms")
            if rtt is None:
                continue
            trend = self.links.get(name)
            if trend is None:
                trend = self.links[name] = RttTrend(
                    settings.rtt_window_samples,
                    settings.rtt_degraded_factor,
                    settings.rtt_degraded_min_ms,
                )
            if trend.add(float(rtt)):
                figures = trend.figures()
                self._warn(
                    "LINK_DEGRADING",
                    f"the {name}'s round trips are degrading: p95 {figures.p95_ms:.1f} ms over "
                    f"the last {figures.samples} looks against {figures.baseline_p95_ms:.1f} ms "
                    "at first: check its cable, switch and the device's load",
                    name,
                )

    # --- runs and parts --------------------------------------------------------------------

    def on_run_ended(self, ended: RunEnded) -> None:
        """A run ended (told in the worker): judged once the worker has yielded."""
        asyncio.get_running_loop().call_soon(self.judge_run, ended)

    def judge_run(self, ended: RunEnded) -> None:
        """Count its outcome in the error rate, and put its part on the charts."""
        try:
            self._judge_run(ended)
        except Exception:  # judging must never fail the cell
            log.exception("the cell's self-watch could not judge run %s", ended.run_id)

    def _judge_run(self, ended: RunEnded) -> None:
        if ended.outcome in ("completed", "failed") and self.errors.add(ended.outcome == "failed"):
            settings = self._settings()
            rate = self.errors.per_100() or 0.0
            failed = sum(self.errors.outcomes)
            self._warn(
                "ERROR_RATE_RISING",
                f"{failed} of the last {len(self.errors.outcomes)} operations failed, "
                f"{rate:.0f} per 100 (over error_rate_alert_per_100, "
                f"{settings.error_rate_alert_per_100:g}): see GET /errors for what failed",
                "system",
                severity="alert",
            )
        inspection = inspection_of(ended.result)
        if inspection is not None:
            good = inspection["verdict"] == "good"
            self.add_part(Point(ended.run_id, time.time(), good, figures_of_summary(inspection)))

    def add_part(self, point: Point, *, quiet: bool = False) -> None:
        """One inspected part on the charts; a figure that starts drifting is warned of
        (not when `quiet`: the history read at start)."""
        self.points.append(point)
        settings = self._settings()
        points = list(self.points)  # the rule slices the series; a deque does not
        for figure in FIGURES:
            drift = drift_of(points, figure, settings)
            if self._drifts[figure.name].rises(drift is not None) and drift and not quiet:
                self._warn(drift.code, drift.message(point.run_id), "quality")

    def trends(self) -> dict[str, Any]:
        """GET /quality/trends: each figure's series and limits, and the rule's settings."""
        settings = self._settings()
        return {
            "parts": len(self.points),
            "baseline_parts": settings.trend_baseline_parts,
            "run_length": settings.trend_run_length,
            "sigma": settings.trend_sigma,
            "charts": charts(list(self.points), settings),
        }

    # --- what is shown ---------------------------------------------------------------------

    def system(self) -> dict[str, Any]:
        """GET /health's `system` block."""
        sample = self.latest or self.look()
        settings = self._settings()
        limit = byte_size(settings.memory_limit) if settings.memory_limit else None
        rate = self.errors.per_100()
        return {
            "cpu_percent": sample.cpu_percent,
            "memory": {
                "used_bytes": sample.memory_bytes,
                "limit_bytes": limit,
                "level": sample.memory_level,
            },
            "server": sample.server.as_dict(),
            "image_process": None if sample.image is None else sample.image.as_dict(),
            "loop_lag_ms": round(sample.loop_lag_s * 1000.0, 3),
            "disk": {
                "path": str(self.data_path),
                "free_bytes": sample.free_bytes,
                "total_bytes": sample.total_bytes,
                "warning_bytes": byte_size(settings.free_space_warning),
            },
            "links": {name: trend.figures().as_dict() for name, trend in self.links.items()},
            "error_rate": {
                "per_100": None if rate is None else round(rate, 1),
                "operations": len(self.errors.outcomes),
                "window": self.errors.outcomes.maxlen,
            },
        }

    # --- the history -----------------------------------------------------------------------

    def _history(self, journal: Journal) -> tuple[list[dict[str, Any]], list[str]]:
        """The latest inspections (oldest first) and operation outcomes, from the journal."""
        rows = journal.query("inspections", limit=CHART_POINTS)
        outcomes = journal.query(
            "operations", limit=self.errors.outcomes.maxlen or 1, newest_first=True
        )
        ended = [row["outcome"] for row in reversed(outcomes) if row["outcome"]]
        return list(reversed(rows)), ended

    def _load(self, inspections: list[dict[str, Any]], outcomes: list[str]) -> None:
        for row in inspections:
            document = _document_of(row["document"])
            point = Point(
                str(row["run_id"]),
                float(row["time"]),
                row["verdict"] == "good",
                figures_of_document(document),
            )
            self.add_part(point, quiet=True)
        self.errors.extend(o == "failed" for o in outcomes if o in ("completed", "failed"))


def _document_of(stored: Any) -> dict[str, Any]:
    """An inspection row's document (JSON text in the journal); {} if it is unreadable, so
    one damaged row leaves a gap in the charts, not a cell that cannot start."""
    if isinstance(stored, dict):
        return stored
    try:
        document = json.loads(stored)
    except (TypeError, ValueError):
        return {}
    return document if isinstance(document, dict) else {}
