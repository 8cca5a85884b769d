"""A Sparkplug B host for the tests: an MQTT client as the broker's `scada` user that
reads every `spBv1.0/...` message with a decoder nobody here wrote (the protobuf runtime
and the code generated from Eclipse Tahu's `sparkplug_b.proto` that esio-spb-builder
ships), and writes NCMD and DCMD with it. It never imports the cell's own codec."""

from __future__ import annotations

import asyncio
import contextlib
import time
import uuid
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from typing import Any

import aiomqtt
from esio_spb_builder.core import sparkplug_b_pb2 as tahu

from tests.mosquitto import WAIT_S, login_of

# Tahu's data type numbers and the value field each uses.
VALUE_FIELD = {
    3: "int_value",  # Int32
    4: "long_value",  # Int64
    8: "long_value",  # UInt64
    10: "double_value",  # Double
    11: "boolean_value",  # Boolean
    12: "string_value",  # String
    13: "long_value",  # DateTime
}
TYPE_NAMES = {3: "Int32", 4: "Int64", 8: "UInt64", 10: "Double", 11: "Boolean", 12: "String"}
TYPE_NAMES[13] = "DateTime"


@dataclass
class Message:
    """One Sparkplug message as the host read it."""

    topic: str
    kind: str  # NBIRTH, DBIRTH, DDATA, NDEATH...
    seq: int | None
    timestamp: int
    metrics: dict[str, tuple[str, Any]] = field(default_factory=dict)  # name: (type, value)

    def value(self, name: str) -> Any:
        return self.metrics[name][1]


def read(topic: str, raw: bytes) -> Message:
    payload = tahu.Payload.FromString(raw)
    metrics = {}
    for metric in payload.metrics:
        kind = TYPE_NAMES.get(metric.datatype, str(metric.datatype))
        if metric.is_null:
            metrics[metric.name] = (kind, None)
            continue
        value = getattr(metric, VALUE_FIELD[metric.datatype])
        if metric.datatype == 3 and value >= 1 << 31:
            value -= 1 << 32
        metrics[metric.name] = (kind, value)
    seq = payload.seq if payload.HasField("seq") else None
    return Message(topic, topic.split("/")[2], seq, payload.timestamp, metrics)


class Host:
    """What arrived, in order, and a way to wait for what a test expects."""

    def __init__(self, client: aiomqtt.Client, group: str) -> None:
        self.client = client
        self.group = group
        self.messages: list[Message] = []
        self._arrived = asyncio.Event()

    def of(self, kind: str) -> list[Message]:
        return [m for m in self.messages if m.kind == kind]

    async def wait(self, check: Callable[[], Any], timeout: float = WAIT_S) -> Any:
        async with asyncio.timeout(timeout):
            while not (found := check()):
                self._arrived.clear()
                await self._arrived.wait()
        return found

    def device_values(self) -> dict[str, Any]:
        """Every device metric as the host knows it: the last DBIRTH, then each DDATA."""
        values: dict[str, Any] = {}
        for message in self.messages:
            if message.kind == "DBIRTH":
                values = {name: value for name, (_, value) in message.metrics.items()}
            elif message.kind == "DDATA":
                values.update({name: value for name, (_, value) in message.metrics.items()})
        return values

    async def rebirth(self, edge_node: str) -> None:
        payload = tahu.Payload(timestamp=int(time.time() * 1000))
        payload.metrics.add(name="Node Control/Rebirth", datatype=11, boolean_value=True)
        topic = f"spBv1.0/{self.group}/NCMD/{edge_node}"
        await self.client.publish(topic, payload.SerializeToString(), qos=0)

    async def command(
        self, edge_node: str, metric: str, *, sent_ms: int | None = None, value: bool = True
    ) -> None:
        payload = tahu.Payload(timestamp=sent_ms or int(time.time() * 1000))
        payload.metrics.add(name=metric, datatype=11, boolean_value=value)
        topic = f"spBv1.0/{self.group}/DCMD/{edge_node}/cell"
        await self.client.publish(topic, payload.SerializeToString(), qos=0)

    def _add(self, message: Message) -> None:
        self.messages.append(message)
        self._arrived.set()


@contextlib.asynccontextmanager
async def sparkplug_host(port: int, group: str, user: str = "scada") -> AsyncIterator[Host]:
    """A host subscribed to `spBv1.0/<group>/#`, collecting in the background; yielded
    once subscribed (a marker it publishes itself has come back)."""
    async with aiomqtt.Client(
        "127.0.0.1", port, identifier=f"host-{uuid.uuid4().hex[:8]}", **login_of(user)
    ) as client:
        host = Host(client, group)
        marker = f"tests/subscribed/{uuid.uuid4().hex}"
        await client.subscribe(f"spBv1.0/{group}/#", qos=1)
        await client.subscribe(marker, qos=1)
        seen = asyncio.Event()

        async def collect() -> None:
            async for message in client.messages:
                topic = str(message.topic)
                if topic == marker:
                    seen.set()
                elif isinstance(message.payload, bytes):
                    host._add(read(topic, message.payload))

        task = asyncio.create_task(collect())
        try:
            async with asyncio.timeout(WAIT_S):
                while not seen.is_set():
                    await client.publish(marker, b"1", qos=1)
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(seen.wait(), 0.2)
            yield host
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
