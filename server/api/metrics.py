"""Prometheus metrics at GET /metrics (text format, prometheus-client).

Counters that the worker already keeps (events processed and refused) and
gauges of the moment (state, queue depth, devices, WebSocket clients) are read
at scrape time; durations are observed as they happen: event processing by the
worker's statistics hook, API requests by a middleware, operations when they
end, transitions by a bus subscriber. Inspected parts are counted as their run
ends, by verdict, with each part's precision and flow consistency observed
(server/quality/part_verdict.py reads the run's inspection); every spray run's
part is counted too, by the verdict every path gives it (`glue_cell_parts_total`).
Each app has its own registry, which holds the standard process and Python
collectors too (`process_*`, `python_gc_*`, `python_info`), and
the build and the plant links (server/api/plant_metrics.py), and the cell's own
resources, link trends and error rate (server/api/watch.py).

By Prometheus's conventions: base units (seconds, metres) and 0-1 ratios, and no
`_created` series (prometheus-client's creation time of each series, which nothing
here reads, doubled every counter and histogram). A part's precision and flow
consistency are exposed in metres and as a ratio; their millimetre and percent
series are kept beside them for one release, marked deprecated in their help, so
dashboards and alerts move over before they go (README, "Changes").
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Iterator
from typing import Any

from fastapi import APIRouter, FastAPI, Request, Response
from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    GCCollector,
    Histogram,
    PlatformCollector,
    ProcessCollector,
    disable_created_metrics,
    generate_latest,
)
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
from prometheus_client.registry import Collector
from starlette.types import Scope

from server.api.declared_query import DeclaredQueryRoute
from server.api.plant_metrics import BuildCollector, PlantCollector
from server.api.schemas import text_body
from server.api.watch import SystemCollector
from server.bootstrap.cell import Cell
from server.core.infra.bus import SubscriptionClosed
from server.core.machine.transitions import State
from server.core.worker.runs import RunEnded
from server.quality.part_verdict import (
    PART_VERDICTS,
    VERDICTS,
    figure_of,
    inspection_of,
    part_verdict,
)

router = APIRouter(tags=["queries"], route_class=DeclaredQueryRoute)
LATENCY_BUCKETS = (0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5)
OPERATION_BUCKETS = (1, 5, 10, 30, 60, 120, 300, 600, 1800)
PRECISION_M_BUCKETS = (0.0001, 0.00025, 0.0005, 0.001, 0.002, 0.005, 0.01)
CV_RATIO_BUCKETS = (0.01, 0.02, 0.05, 0.1, 0.2, 0.5)
# The deprecated series' buckets: the same bounds in millimetres and percent.
PRECISION_MM_BUCKETS = (0.1, 0.25, 0.5, 1, 2, 5, 10)
CV_PERCENT_BUCKETS = (1, 2, 5, 10, 20, 50)
MM_PER_M = 1000.0
PERCENT_PER_RATIO = 100.0


class CellCollector(Collector):
    """Values read from the running cell at each scrape."""

    def __init__(self, app: FastAPI) -> None:
        self.app = app

    def collect(self) -> Iterator[GaugeMetricFamily | CounterMetricFamily]:
        cell: Cell = self.app.state.cell
        if not cell.started:
            return
        view = cell.view
        state = GaugeMetricFamily("glue_cell_state", "1 for the current state", labels=["state"])
        for candidate in State:
            state.add_metric([candidate.value], 1.0 if view.state is candidate else 0.0)
        yield state
        performance = view.performance()
        processed = CounterMetricFamily("glue_cell_events_processed", "events decided")
        processed.add_metric([], performance["events_processed"])
        yield processed
        refused = CounterMetricFamily("glue_cell_events_refused", "events refused")
        refused.add_metric([], performance["events_refused"])
        yield refused
        depth = GaugeMetricFamily("glue_cell_event_queue_depth", "events waiting")
        depth.add_metric([], performance["queue_size"])
        yield depth
        clients = GaugeMetricFamily("glue_cell_websocket_clients", "connected /ws clients")
        clients.add_metric([], self.app.state.ws_hub.client_count)
        yield clients
        connected = GaugeMetricFamily(
            "glue_cell_device_connected", "1 when the device answers", labels=["device"]
        )
        rtt = GaugeMetricFamily(
            "glue_cell_device_rtt_seconds", "last round trip", labels=["device"]
        )
        for name, health in cell.devices.health().items():
            connected.add_metric([name], 1.0 if health["connected"] else 0.0)
            if health["last_rtt_ms"] is not None:
                rtt.add_metric([name], health["last_rtt_ms"] / 1000.0)
        yield connected
        yield rtt


class Metrics:
    """The app's registry and the metrics observed as things happen."""

    def __init__(self, app: FastAPI) -> None:
        # prometheus-client's switch is the process's, not a registry's: this process
        # serves one cell, and none of its registries wants `_created` series.
        disable_created_metrics()
        self.registry = CollectorRegistry()
        self.registry.register(CellCollector(app))
        self.registry.register(PlantCollector(app))
        self.registry.register(BuildCollector())
        self.registry.register(SystemCollector(app))
        ProcessCollector(registry=self.registry)
        PlatformCollector(registry=self.registry)
        GCCollector(registry=self.registry)
        self.event_seconds = Histogram(
            "glue_cell_event_processing_seconds",
            "time to decide and act on one event",
            buckets=LATENCY_BUCKETS,
            registry=self.registry,
        )
        self.request_seconds = Histogram(
            "glue_cell_api_request_seconds",
            "HTTP request latency",
            ["method", "route", "status"],
            buckets=LATENCY_BUCKETS,
            registry=self.registry,
        )
        self._request_children: dict[tuple[str, str, int], Any] = {}
        self.operation_seconds = Histogram(
            "glue_cell_operation_duration_seconds",
            "operation run time",
            ["kind", "outcome"],
            buckets=OPERATION_BUCKETS,
            registry=self.registry,
        )
        self.transitions = Counter(
            "glue_cell_transitions",
            "state transitions",
            ["old_state", "new_state"],
            registry=self.registry,
        )
        self.parts_inspected = Counter(
            "glue_cell_parts_inspected",
            "parts inspected after their run, by verdict",
            ["verdict"],
            registry=self.registry,
        )
        for verdict in VERDICTS:  # both series exist from the start, at 0
            self.parts_inspected.labels(verdict)
        self.parts = Counter(
            "glue_cell_parts",
            "every spray run's part by the verdict every path gives it: good, defective "
            "(a run that did not complete included), not_inspected",
            ["verdict"],
            registry=self.registry,
        )
        for verdict in PART_VERDICTS:
            self.parts.labels(verdict)
        self.part_precision_m = Histogram(
            "glue_cell_part_trajectory_precision_meters",
            "each inspected part's p95 deviation from the planned spray path, in metres",
            buckets=PRECISION_M_BUCKETS,
            registry=self.registry,
        )
        self.part_dispensing_cv = Histogram(
            "glue_cell_part_dispensing_cv_ratio",
            "each inspected part's flow coefficient of variation while spraying (0-1)",
            buckets=CV_RATIO_BUCKETS,
            registry=self.registry,
        )
        self.part_precision_mm = Histogram(
            "glue_cell_part_trajectory_precision_mm",
            "DEPRECATED, removed in the next release: use "
            "glue_cell_part_trajectory_precision_meters (the same in millimetres)",
            buckets=PRECISION_MM_BUCKETS,
            registry=self.registry,
        )
        self.part_dispensing_cv_percent = Histogram(
            "glue_cell_part_dispensing_cv_percent",
            "DEPRECATED, removed in the next release: use "
            "glue_cell_part_dispensing_cv_ratio (the same in percent)",
            buckets=CV_PERCENT_BUCKETS,
            registry=self.registry,
        )
        self._watcher: asyncio.Task[None] | None = None

    def attach(self, cell: Cell) -> None:
        """Hook into the running cell (after it started)."""
        view = cell.view
        view.on_event_decided(self.event_seconds.observe)
        view.on_run_ended(self.observe_run)
        self._watcher = asyncio.create_task(self._count_transitions(cell), name="metrics")

    def observe_run(self, ended: RunEnded) -> None:
        """A run ended (in the worker: only counts): its duration, and its part if inspected."""
        self.operation_seconds.labels(ended.operation, ended.outcome).observe(ended.seconds)
        if ended.operation == "trajectory":
            self.parts.labels(part_verdict(ended.outcome, ended.result, ended.error).verdict).inc()
        inspection = inspection_of(ended.result)
        if inspection is None:
            return
        self.parts_inspected.labels(inspection["verdict"]).inc()
        precision = figure_of(inspection, "precision_p95_mm")
        if precision is not None:
            self.part_precision_m.observe(precision / MM_PER_M)
            self.part_precision_mm.observe(precision)
        cv = figure_of(inspection, "dispensing_cv_percent")
        if cv is not None:
            self.part_dispensing_cv.observe(cv / PERCENT_PER_RATIO)
            self.part_dispensing_cv_percent.observe(cv)

    async def detach(self) -> None:
        if self._watcher is not None:
            self._watcher.cancel()
            await asyncio.gather(self._watcher, return_exceptions=True)

    async def _count_transitions(self, cell: Cell) -> None:
        subscription = cell.bus.subscribe(1024, types=["state_changed"])
        while True:
            try:
                message = await subscription.get()
            except SubscriptionClosed:  # fell behind: start again, the counters stay
                subscription = cell.bus.subscribe(1024, types=["state_changed"])
                continue
            self.transitions.labels(message.data["old_state"], message.data["new_state"]).inc()

    def observe_response(self, scope: Scope, status: int, seconds: float) -> None:
        """Request duration by method, route template and status (an observer)."""
        path = getattr(scope.get("route"), "path", "unmatched")
        key = (scope["method"], path, status)  # bounded: route templates, not raw paths
        with contextlib.suppress(Exception):
            child = self._request_children.get(key)
            if child is None:  # labels() resolves the child by name: once per key, not per call
                child = self._request_children[key] = self.request_seconds.labels(
                    key[0], path, str(status)
                )
            child.observe(seconds)


@router.get(
    "/metrics", response_class=Response, responses={200: {"content": text_body("text/plain")}}
)
async def metrics(request: Request) -> Response:
    """Prometheus text exposition of the cell's metrics."""
    registry = request.app.state.metrics.registry
    return Response(generate_latest(registry), media_type=CONTENT_TYPE_LATEST)
