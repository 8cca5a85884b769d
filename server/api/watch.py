"""The cell watching itself, as the API shows it: `system` in GET /health, its series in
GET /metrics, and GET /quality/trends (the control charts of the parts' figures).

The figures come from the cell's `CellWatch` (server/watch/watcher.py), read at each
request or scrape; nothing here samples or judges.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from fastapi import APIRouter, FastAPI, HTTPException, Request
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
from prometheus_client.registry import Collector
from pydantic import BaseModel, Field

from server.api.declared_query import DeclaredQueryRoute
from server.bootstrap.cell import Cell

router = APIRouter(tags=["queries"], route_class=DeclaredQueryRoute)


class ProcessView(BaseModel):
    """One process of the cell (the server, or its image process)."""

    pid: int
    resident_bytes: int | None = Field(description="resident memory (VmRSS)")
    unique_bytes: int | None = Field(
        description="memory the process alone holds (Private_* of smaps_rollup)"
    )
    threads: int | None
    open_files: int | None = Field(description="open file descriptors")
    cpu_seconds: float | None = Field(description="user and system CPU time used")


class MemoryView(BaseModel):
    used_bytes: int | None = Field(description="the server's resident memory")
    limit_bytes: int | None = Field(description="memory_limit; None when not watched")
    level: str = Field(description="ok, warning (memory_warning_percent) or alert (the limit)")


class DiskView(BaseModel):
    path: str = Field(description="the data directory")
    free_bytes: int | None
    total_bytes: int | None
    warning_bytes: int = Field(description="free_space_warning")


class LinkTrendView(BaseModel):
    p95_ms: float | None = Field(description="p95 round trip of the latest window")
    baseline_p95_ms: float | None = Field(description="p95 of the first full window")
    samples: int


class ErrorRateView(BaseModel):
    per_100: float | None = Field(description="failed operations per 100 in the window")
    operations: int
    window: int | None


class SystemHealthView(BaseModel):
    """The cell's own resources (docs/operations-guide.md, "Monitoring")."""

    cpu_percent: float | None = Field(description="both processes, percent of one core")
    memory: MemoryView
    server: ProcessView
    image_process: ProcessView | None = Field(description="the image process, while it runs")
    loop_lag_ms: float = Field(description="the event loop's largest lag since the last look")
    disk: DiskView
    links: dict[str, LinkTrendView] = Field(description="each device's round-trip trend")
    error_rate: ErrorRateView


def system_of(cell: Cell) -> dict[str, Any] | None:
    return cell.watch.system() if cell.watch is not None else None


@router.get("/quality/trends", responses={503: {"description": "the cell is not started"}})
async def get_trends(request: Request) -> dict[str, Any]:
    """Each part figure's control chart: the series of inspected parts, the centre line and
    limits from the last good parts, and the drift the latest part shows, if any
    (docs/quality.md, "Trends")."""
    cell: Cell = request.app.state.cell
    if cell.watch is None:
        raise HTTPException(503, "the cell is not started")
    return cell.watch.trends()


class SystemCollector(Collector):
    """The watch's figures at each scrape (none until the cell has started)."""

    def __init__(self, app: FastAPI) -> None:
        self.app = app

    def collect(self) -> Iterator[GaugeMetricFamily | CounterMetricFamily]:
        cell: Cell = self.app.state.cell
        if cell.watch is None:
            return
        system = cell.watch.system()
        memory = GaugeMetricFamily(
            "glue_cell_memory_bytes",
            "memory of the cell's processes: resident, and unique (private to the process)",
            labels=["process", "kind"],
        )
        threads = GaugeMetricFamily("glue_cell_threads", "threads", labels=["process"])
        files = GaugeMetricFamily(
            "glue_cell_open_files", "open file descriptors", labels=["process"]
        )
        cpu = CounterMetricFamily("glue_cell_cpu_seconds", "CPU time used", labels=["process"])
        for name, process in (("server", system["server"]), ("image", system["image_process"])):
            if process is None:
                continue
            for kind in ("resident", "unique"):
                if process[f"{kind}_bytes"] is not None:
                    memory.add_metric([name, kind], process[f"{kind}_bytes"])
            if process["threads"] is not None:
                threads.add_metric([name], process["threads"])
            if process["open_files"] is not None:
                files.add_metric([name], process["open_files"])
            if process["cpu_seconds"] is not None:
                cpu.add_metric([name], process["cpu_seconds"])
        yield from (memory, threads, files, cpu)
        limit = system["memory"]["limit_bytes"]
        if limit is not None:
            yield GaugeMetricFamily(
                "glue_cell_memory_limit_bytes", "memory_limit", value=float(limit)
            )
        yield GaugeMetricFamily(
            "glue_cell_event_loop_lag_seconds",
            "the event loop's largest lag since the watch's last look",
            value=system["loop_lag_ms"] / 1000.0,
        )
        disk = system["disk"]
        if disk["free_bytes"] is not None:
            yield GaugeMetricFamily(
                "glue_cell_data_free_bytes",
                "free space of the data directory's disk",
                value=float(disk["free_bytes"]),
            )
            yield GaugeMetricFamily(
                "glue_cell_data_size_bytes",
                "size of the data directory's disk",
                value=float(disk["total_bytes"]),
            )
        rtt = GaugeMetricFamily(
            "glue_cell_device_rtt_p95_seconds",
            "p95 round trip of the latest window, per device",
            labels=["device"],
        )
        for name, link in system["links"].items():
            if link["p95_ms"] is not None:
                rtt.add_metric([name], link["p95_ms"] / 1000.0)
        yield rtt
        rate = system["error_rate"]["per_100"]
        if rate is not None:
            yield GaugeMetricFamily(
                "glue_cell_operation_error_ratio",
                "failed operations among the latest in the error rate's window (0-1)",
                value=rate / 100.0,
            )
