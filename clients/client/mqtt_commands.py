"""Commands over MQTT: signed, sent to one cell, answered on a response topic.

`AsyncMqttCommands` (asyncio) and `MqttCellClient` (blocking, what `gluectl --mqtt`
uses) publish each command on `<prefix>/<cell_id>/command/<name>`, signed by
`mqtt_signing.sign_command` (the token's secret never goes on the wire, and a copy
replayed later or again is refused by the cell), with an MQTT v5 response topic
(`<prefix>/<cell_id>/response/<random>`, which the broker's ACL lets senders read and
the cell write) and correlation data, and wait for the answer. The answer is the
HTTP answer's JSON with its status beside it; it is read exactly as the HTTP
clients read theirs: a `CommandResult` for 202, else the same typed exceptions
(Refused, Unauthorized, Forbidden, InvalidRequest, Busy, ...).

The command methods are the HTTP clients' (start, pause, resume, cancel, estop,
reset, home, jog, calibrate_robot, calibrate_camera, create_workpiece), so a
script moves from HTTP to MQTT by changing its client.
"""

from __future__ import annotations

import asyncio
import json
import ssl
import uuid
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Self
from urllib.parse import urlsplit

import aiomqtt
import httpx
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from clients.client import builders
from clients.client.errors import CommandResult, ServerError, Unreachable
from clients.client.mqtt_signing import sign_command

DEFAULT_PREFIX = "glue"


@dataclass(frozen=True)
class MqttTarget:
    """Which broker, as whom, and which cell: everything but the API token."""

    url: str  # mqtt://host[:port] or mqtts://host[:port]
    cell_id: str
    prefix: str = DEFAULT_PREFIX
    username: str | None = None
    password: str | None = None
    ca_file: Path | None = None

    def __repr__(self) -> str:  # the broker password never shows
        return f"MqttTarget({self.url!r}, cell_id={self.cell_id!r}, username={self.username!r})"

    def address(self) -> tuple[str, int, bool]:
        """Host, port and whether TLS; ValueError for what is not an MQTT URL."""
        parts = urlsplit(self.url)
        if parts.scheme not in ("mqtt", "mqtts") or not parts.hostname:
            raise ValueError(f"not a broker address: {self.url!r} (expected mqtt://host:port)")
        tls = parts.scheme == "mqtts"
        return parts.hostname, parts.port or (8883 if tls else 1883), tls


class AsyncMqttCommands:
    """One connection to the broker; each command signed, published and answered."""

    def __init__(self, target: MqttTarget, token: str | None, *, timeout: float = 10.0) -> None:
        self.target = target
        self._token = token
        self.timeout = timeout
        self._client: aiomqtt.Client | None = None
        self._reply_to = f"{target.prefix}/{target.cell_id}/response/{uuid.uuid4().hex}"
        self._lock = asyncio.Lock()  # one command at a time on this connection

    def __repr__(self) -> str:
        return f"AsyncMqttCommands({self.target!r})"

    async def __aenter__(self) -> Self:
        host, port, tls = self.target.address()
        context = None
        if tls:
            ca = str(self.target.ca_file) if self.target.ca_file else None
            context = ssl.create_default_context(cafile=ca)
        self._client = aiomqtt.Client(
            host,
            port,
            username=self.target.username,
            password=self.target.password,
            protocol=aiomqtt.ProtocolVersion.V5,
            tls_context=context,
            timeout=self.timeout,
        )
        try:
            await self._client.__aenter__()
            await self._client.subscribe(self._reply_to, qos=1)
        except aiomqtt.MqttError as error:
            self._client = None
            raise Unreachable(f"cannot reach the broker {host}:{port}: {error}") from None
        return self

    async def __aexit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        client, self._client = self._client, None
        if client is not None:
            await client.__aexit__(kind, error, traceback)

    async def command(self, name: str, body: dict[str, Any] | None = None) -> CommandResult:
        """Send one command; its CommandResult (202), else the HTTP clients' exception."""
        builders.command(name, body)  # an unknown name is a ValueError here, as over HTTP
        if self._client is None:
            raise RuntimeError("use `async with AsyncMqttCommands(...)` first")
        if not self._token:
            raise ValueError("no API token: commands over MQTT are signed with one")
        topic = f"{self.target.prefix}/{self.target.cell_id}/command/{name}"
        message = sign_command(self._token, topic, body)
        correlation = uuid.uuid4().bytes
        properties = Properties(PacketTypes.PUBLISH)
        properties.ResponseTopic = self._reply_to
        properties.CorrelationData = correlation
        async with self._lock:
            try:
                await self._client.publish(
                    topic, json.dumps(message).encode(), qos=1, properties=properties
                )
                async with asyncio.timeout(self.timeout):
                    async for answer in self._client.messages:
                        got = getattr(answer.properties, "CorrelationData", None)
                        if got == correlation:
                            return _result(answer.payload)
            except TimeoutError:
                raise Unreachable(
                    f"no answer from cell {self.target.cell_id!r} within {self.timeout:g} s "
                    "(is mqtt_commands on, the cell id right, the cell connected?)"
                ) from None
            except aiomqtt.MqttError as error:
                raise Unreachable(f"lost the broker: {error}") from None
        raise Unreachable("the broker closed the connection before the answer")

    async def send(self, call: builders.Call[CommandResult]) -> CommandResult:
        """A command as the HTTP clients build it (builders.start(...) and the like)."""
        return await self.command(call.path.lstrip("/"), call.json)

    async def start(
        self, workpiece_id: str | None = None, contour_matching: bool = True
    ) -> CommandResult:
        """Start spraying (IDLE → EXECUTING_TRAJECTORY)."""
        return await self.send(builders.start(workpiece_id, contour_matching))

    async def estop(self, reason: str | None = None) -> CommandResult:
        """Software stop (any role)."""
        return await self.send(builders.estop(reason))

    async def jog(self, axis: str, distance_mm: float) -> CommandResult:
        return await self.send(builders.jog(axis, distance_mm))

    async def create_workpiece(
        self, name: str | None = None, workpiece_id: str | None = None, if_new: bool = False
    ) -> CommandResult:
        return await self.send(builders.create_workpiece(name, workpiece_id, if_new))


def _result(payload: Any) -> CommandResult:
    """The answer on the response topic, read as the HTTP clients read an answer."""
    try:
        answer = json.loads(bytes(payload))
        status = int(answer.pop("status"))
    except (ValueError, TypeError, KeyError, AttributeError):
        raise ServerError(f"unexpected answer on the response topic: {payload!r:.200}") from None
    response = httpx.Response(status, json=answer)
    if status != 202:
        raise builders.error_of(response)
    return builders.command_result(response, answer)


class MqttCellClient:
    """The blocking form: each command one connection, for scripts and gluectl."""

    def __init__(self, target: MqttTarget, token: str | None, *, timeout: float = 10.0) -> None:
        self.target = target
        self._token = token
        self.timeout = timeout

    def __repr__(self) -> str:
        return f"MqttCellClient({self.target!r})"

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *_: object) -> None:
        return None

    def command(self, name: str, body: dict[str, Any] | None = None) -> CommandResult:
        async def send() -> CommandResult:
            async with AsyncMqttCommands(self.target, self._token, timeout=self.timeout) as c:
                return await c.command(name, body)

        return asyncio.run(send())

    def _send(self, call: builders.Call[CommandResult]) -> CommandResult:
        return self.command(call.path.lstrip("/"), call.json)

    def start(
        self, workpiece_id: str | None = None, contour_matching: bool = True
    ) -> CommandResult:
        """Start spraying (IDLE → EXECUTING_TRAJECTORY)."""
        return self._send(builders.start(workpiece_id, contour_matching))

    def pause(self) -> CommandResult:
        return self.command("pause")

    def resume(self) -> CommandResult:
        return self.command("resume")

    def cancel(self) -> CommandResult:
        return self.command("cancel")

    def estop(self, reason: str | None = None) -> CommandResult:
        """Software stop (any role). A stop not answered is not known to be made."""
        return self._send(builders.estop(reason))

    def reset(self) -> CommandResult:
        return self.command("reset")

    def home(self) -> CommandResult:
        return self.command("home")

    def purge(self) -> CommandResult:
        return self.command("purge")

    def jog(self, axis: str, distance_mm: float) -> CommandResult:
        return self._send(builders.jog(axis, distance_mm))

    def calibrate_robot(self) -> CommandResult:
        return self.command("calibrate-robot")

    def calibrate_camera(self) -> CommandResult:
        return self.command("calibrate-camera")

    def create_workpiece(
        self, name: str | None = None, workpiece_id: str | None = None, if_new: bool = False
    ) -> CommandResult:
        return self._send(builders.create_workpiece(name, workpiece_id, if_new))
