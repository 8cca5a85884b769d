"""Watch a line of cells on an MQTT broker (paho): a snapshot for scripts, or live.

`gluectl line` reads the cells from the plant's broker, not from each cell's HTTP
API: the broker already holds every cell's retained state, and a dead cell's last
will (`offline`), so one connection sees the whole line, whichever cells are down.

A snapshot needs to know when the broker has sent every retained message. MQTT has
no marker for that, so the watcher subscribes to the cells' topics and then to a
second, unused filter: the broker answers subscriptions in order and queues a
subscription's retained messages before it reads the next packet, so the second
acknowledgement arrives after the first one's retained messages. No waiting for a
quiet period. Subscriptions are QoS 0: the view is a picture of the retained state,
and QoS 0 messages are not held back by the broker's in-flight window.
"""

from __future__ import annotations

import queue
import ssl
import threading
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlsplit

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

from clients.line_model import DEFAULT_PREFIX, LineModel

DEFAULT_PORTS = {"mqtt": 1883, "mqtts": 8883}
KEEPALIVE_S = 30


class LineUnreachable(Exception):
    """The broker could not be reached, or refused the connection."""


@dataclass(frozen=True)
class Broker:
    """Where the broker is: `mqtt://host:port` (or `mqtts://`, TLS with the system's CAs)."""

    host: str
    port: int
    tls: bool = False
    username: str | None = None
    password: str | None = None

    @classmethod
    def parse(cls, url: str) -> Broker:
        parts = urlsplit(url)
        if parts.scheme not in DEFAULT_PORTS or not parts.hostname:
            raise ValueError(f"not a broker address: {url!r} (expected mqtt://host:port)")
        try:
            port = parts.port or DEFAULT_PORTS[parts.scheme]
        except ValueError as error:
            raise ValueError(f"not a broker address: {url!r} ({error})") from None
        return cls(parts.hostname, port, parts.scheme == "mqtts", parts.username, parts.password)

    def __str__(self) -> str:
        return f"{'mqtts' if self.tls else 'mqtt'}://{self.host}:{self.port}"


def _client(broker: Broker) -> mqtt.Client:
    client = mqtt.Client(
        CallbackAPIVersion.VERSION2, client_id=f"gluectl-line-{uuid.uuid4().hex[:12]}"
    )
    if broker.tls:
        client.tls_set(cert_reqs=ssl.CERT_REQUIRED)
    if broker.username is not None:
        client.username_pw_set(broker.username, broker.password)
    return client


class LineWatcher:
    """One connection to the broker, folding every cell's messages into a LineModel.

    paho's network thread only queues what it hears; the caller's thread applies it,
    so the model is never shared between threads.
    """

    def __init__(self, broker: Broker, prefix: str = DEFAULT_PREFIX) -> None:
        self.broker = broker
        self.model = LineModel(prefix)
        self._inbox: queue.Queue[tuple[str, Any]] = queue.Queue()
        self._client = _client(broker)
        self._barrier_mid: int | None = None
        self._client.on_connect = self._on_connect
        self._client.on_subscribe = self._on_subscribe
        self._client.on_message = self._on_message
        self._client.on_disconnect = self._on_disconnect

    # paho's thread ---------------------------------------------------------------------
    def _on_connect(self, client: mqtt.Client, _u: Any, _f: Any, code: Any, _p: Any) -> None:
        if code.is_failure:
            self._inbox.put(("refused", str(code)))
            return
        prefix = self.model.prefix
        client.subscribe(f"{prefix}/+/+", qos=0)
        _, self._barrier_mid = client.subscribe(f"{prefix}/+/+/line-snapshot-barrier", qos=0)

    def _on_subscribe(self, _c: Any, _u: Any, mid: int, _codes: Any, _p: Any) -> None:
        if mid == self._barrier_mid:
            self._inbox.put(("snapshot", None))

    def _on_message(self, _c: Any, _u: Any, message: mqtt.MQTTMessage) -> None:
        self._inbox.put(("message", (message.topic, message.payload)))

    def _on_disconnect(self, _c: Any, _u: Any, _f: Any, code: Any, _p: Any) -> None:
        self._inbox.put(("disconnected", str(code)))

    # the caller's thread ---------------------------------------------------------------
    def connect(self, timeout: float) -> None:
        """Connect (paho reconnects by itself afterwards); LineUnreachable if it cannot."""
        try:
            self._client.connect_timeout = timeout
            self._client.connect(self.broker.host, self.broker.port, keepalive=KEEPALIVE_S)
        except OSError as error:
            raise LineUnreachable(f"cannot reach the broker at {self.broker}: {error}") from None
        self._client.loop_start()

    def close(self) -> None:
        self._client.disconnect()
        self._client.loop_stop()

    def next_event(self, timeout: float | None) -> tuple[str, Any]:
        """Apply the next thing heard; ("timeout", None) if nothing came in `timeout` s."""
        try:
            kind, value = self._inbox.get(timeout=timeout)
        except queue.Empty:
            return "timeout", None
        if kind == "message":
            self.model.apply(*value)
        elif kind == "refused":
            raise LineUnreachable(f"the broker at {self.broker} refused the connection: {value}")
        return kind, value

    def snapshot(self, timeout: float) -> LineModel:
        """Every cell's retained state, as soon as the broker has sent all of it."""
        while True:
            kind, _ = self.next_event(timeout)
            if kind == "snapshot":
                return self.model
            if kind == "timeout":
                raise LineUnreachable(f"no answer from the broker at {self.broker} in {timeout} s")

    def follow(self, on_change: Callable[[LineModel], None], stop: threading.Event) -> None:
        """Call `on_change` after each message, until `stop` is set."""
        while not stop.is_set():
            kind, _ = self.next_event(0.5)
            if kind in ("message", "snapshot"):
                on_change(self.model)
