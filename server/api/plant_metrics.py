"""The build and the plant links in Prometheus: read from the running app at each scrape.

- `glue_cell_build_info{version, revision, python_version, python_implementation}`,
  always 1: the usual way to expose a build (join it onto other series by `instance`).
- The MQTT link (when `mqtt_url` is set): connected, reconnects, messages dropped
  while the broker was away, and the messages waiting for it; the same figures as
  `mqtt` in GET /health.
- The OPC UA server (when `opcua_endpoint` is set): the client sessions open on it.
- Each webhook, by its name only (its URL, path and query are its receiver's secret):
  each notice's final outcome counted (delivered, refused, failed, dropped, abandoned:
  every one but `delivered` is a delivery failure), and the notices queued.

The links are reached through the app's state (`mqtt`, `opcua`, `webhooks`: the
composition root's, server/bootstrap/app.py), each None when it is not configured,
so a link that is off has no series.
The transports sit beside this layer, not below it: they are read through the small
protocols here, never imported.
"""

from __future__ import annotations

import platform
from collections.abc import Iterator, Sequence
from typing import Any, Protocol

from fastapi import FastAPI
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, InfoMetricFamily
from prometheus_client.registry import Collector

from server.common.build import package_version, source_revision

# A webhook's final outcomes (server/notify/deliverer.py: `Counters`), each a series.
WEBHOOK_OUTCOMES = ("delivered", "refused", "failed", "dropped", "abandoned")

Family = GaugeMetricFamily | CounterMetricFamily | InfoMetricFamily


class DeliveryFigures(Protocol):
    def status(self) -> dict[str, Any]: ...


class WebhookFigures(Protocol):
    @property
    def deliverers(self) -> Sequence[DeliveryFigures]: ...


class MqttFigures(Protocol):
    def health(self) -> dict[str, Any]: ...


class OpcUaFigures(Protocol):
    def session_count(self) -> int: ...


class BuildCollector(Collector):
    """`glue_cell_build_info`: what is running, read once (it does not change)."""

    def __init__(self) -> None:
        self.labels = {
            "version": package_version(),
            "revision": source_revision(),
            "python_version": platform.python_version(),
            "python_implementation": platform.python_implementation(),
        }

    def collect(self) -> Iterator[Family]:
        # InfoMetricFamily exposes `<name>_info`: named glue_cell_build here.
        info = InfoMetricFamily("glue_cell_build", "the running build of the cell server")
        info.add_metric([], self.labels)
        yield info


class PlantCollector(Collector):
    """The MQTT link, the OPC UA sessions and the webhooks, as they are at each scrape."""

    def __init__(self, app: FastAPI) -> None:
        self.app = app

    def collect(self) -> Iterator[Family]:
        mqtt: MqttFigures | None = getattr(self.app.state, "mqtt", None)
        if mqtt is not None:
            yield from mqtt_families(mqtt.health())
        opcua: OpcUaFigures | None = getattr(self.app.state, "opcua", None)
        if opcua is not None:
            sessions = GaugeMetricFamily(
                "glue_cell_opcua_sessions", "client sessions open on the OPC UA server"
            )
            sessions.add_metric([], opcua.session_count())
            yield sessions
        notifier: WebhookFigures | None = getattr(self.app.state, "webhooks", None)
        if notifier is not None and notifier.deliverers:
            yield from webhook_families([d.status() for d in notifier.deliverers])


def mqtt_families(health: dict[str, Any]) -> Iterator[Family]:
    """The MQTT link's series from what /health shows of it (`MqttLink.health`)."""
    connected = GaugeMetricFamily(
        "glue_cell_mqtt_connected", "1 while the MQTT link is connected to the broker"
    )
    connected.add_metric([], 1.0 if health["connected"] else 0.0)
    yield connected
    reconnects = CounterMetricFamily(
        "glue_cell_mqtt_reconnects", "connections to the broker made after the first"
    )
    reconnects.add_metric([], health["reconnects"])
    yield reconnects
    dropped = CounterMetricFamily(
        "glue_cell_mqtt_messages_dropped",
        "event, progress and alert messages dropped because the buffer (mqtt_buffer) was "
        "full while the broker was away",
    )
    dropped.add_metric([], health["dropped"])
    yield dropped
    backlog = GaugeMetricFamily(
        "glue_cell_mqtt_backlog_messages", "messages waiting to be sent to the broker"
    )
    backlog.add_metric([], health["buffered"])
    yield backlog


def webhook_families(statuses: list[dict[str, Any]]) -> Iterator[Family]:
    """Each webhook's outcomes and queue, labelled by its name (never its URL)."""
    outcomes = CounterMetricFamily(
        "glue_cell_webhook_deliveries",
        "notices whose delivery ended, by webhook name and outcome (every outcome but "
        "delivered is a failure)",
        labels=["webhook", "outcome"],
    )
    queued = GaugeMetricFamily(
        "glue_cell_webhook_queued_notices",
        "notices waiting for their webhook, by webhook name",
        labels=["webhook"],
    )
    for status in statuses:
        for outcome in WEBHOOK_OUTCOMES:
            outcomes.add_metric([status["name"], outcome], status[outcome])
        queued.add_metric([status["name"]], status["queued"])
    yield outcomes
    yield queued
