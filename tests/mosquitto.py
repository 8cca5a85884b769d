"""Debian's mosquitto as a process of the test: a config file in the test's directory,
a listener on a free loopback port, stopped and started again on the same port.

It has the shipped access control (deploy/mosquitto/acl, the password file made as
the line demo makes it, with its demo passwords): anonymous clients are refused, the
cell signs in as `cell`, a plant's subscriber as `line-view`, a sender of commands as
`operator`. One line is added for the tests alone: every user may read and write
`tests/#`, where `subscriber` publishes the marker that tells it it is subscribed.

Persistence is on, so a subscriber's persistent session (clean session off, QoS 1)
and the messages queued for it outlive a restart of the broker, as in a plant."""

from __future__ import annotations

import asyncio
import contextlib
import getpass
import shutil
import socket
import subprocess
import time
import uuid
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path
from typing import Any

import aiomqtt

from server.line.broker import DEMO_PASSWORDS, write_access_files
from tests.serving import free_port

MOSQUITTO = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
WAIT_S = 60.0  # a bound on something happening, never a performance assertion


class Mosquitto:
    """One broker: `start()`, `stop()`, `start()` again on the same port."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self.port = free_port()
        self.config = directory / "mosquitto.conf"
        write_access_files(directory)
        with (directory / "acl").open("a") as acl:
            acl.write("\n# The tests' marker topic, for every user.\npattern readwrite tests/#\n")
        self.config.write_text(
            "per_listener_settings true\n"
            f"listener {self.port} 127.0.0.1\n"
            "allow_anonymous false\n"
            f"password_file {directory / 'passwd'}\n"
            f"acl_file {directory / 'acl'}\n"
            # Started as root, mosquitto would drop to its own user, who cannot write here.
            f"user {getpass.getuser()}\n"
            "persistence true\n"
            f"persistence_location {directory}/\n"
            f"log_dest file {directory}/mosquitto.log\n"
        )
        self.process: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"mqtt://127.0.0.1:{self.port}"

    @property
    def cell_login(self) -> dict[str, str]:
        """The cell's settings for this broker: its URL, user and password."""
        return {
            "mqtt_url": self.url,
            "mqtt_username": "cell",
            "mqtt_password": DEMO_PASSWORDS["cell"],
        }

    @property
    def cell_environment(self) -> dict[str, str]:
        """The same as a server process's environment."""
        return {f"GLUE_APP_{key.upper()}": value for key, value in self.cell_login.items()}

    def start(self) -> None:
        self.process = subprocess.Popen([MOSQUITTO, "-c", str(self.config)])
        deadline = time.monotonic() + WAIT_S
        while True:
            assert self.process.poll() is None, (self.directory / "mosquitto.log").read_text()
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", self.port)):
                return
            assert time.monotonic() < deadline, "mosquitto did not come up"
            time.sleep(0.02)

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()  # mosquitto saves its persistence file on the way out
            self.process.wait(30)
        self.process = None


@contextlib.contextmanager
def mosquitto(directory: Path) -> Iterator[Mosquitto]:
    directory.mkdir(parents=True, exist_ok=True)
    broker = Mosquitto(directory)
    broker.start()
    try:
        yield broker
    finally:
        broker.stop()


class Subscriber:
    """What arrived on which topic, in order, with a wait for what a test expects."""

    def __init__(self) -> None:
        self.messages: list[aiomqtt.Message] = []
        self._arrived = asyncio.Event()

    def on(self, topic: str) -> list[Any]:
        """The payloads received on `topic`, decoded (JSON when they are)."""
        return [_decoded(m.payload) for m in self.messages if str(m.topic) == topic]

    async def wait(self, check: Callable[[], Any], timeout: float = WAIT_S) -> Any:
        """Until `check()` is truthy; its value."""
        async with asyncio.timeout(timeout):
            while not (found := check()):
                self._arrived.clear()
                await self._arrived.wait()
        return found

    def _add(self, message: aiomqtt.Message) -> None:
        self.messages.append(message)
        self._arrived.set()


def login_of(user: str) -> dict[str, str]:
    """aiomqtt's username and password for one of the demo users."""
    return {"username": user, "password": DEMO_PASSWORDS[user]}


def _decoded(payload: Any) -> Any:
    import json

    text = bytes(payload).decode()
    try:
        return json.loads(text)
    except ValueError:
        return text


@contextlib.asynccontextmanager
async def subscriber(
    port: int,
    topic: str,
    *,
    identifier: str | None = None,
    persistent: bool = False,
    user: str = "line-view",
) -> AsyncIterator[Subscriber]:
    """An aiomqtt client subscribed to `topic` at QoS 1, collecting in the background;
    `persistent`: a session the broker keeps (and queues for) while it is away, which
    reconnects by itself when the broker restarts. It signs in as `user` (the line view
    by default: what a plant's dashboard may read)."""
    received = Subscriber()
    login = login_of(user)

    async def collect() -> None:
        while True:
            try:
                async with aiomqtt.Client(
                    "127.0.0.1",
                    port,
                    identifier=identifier,
                    clean_session=not persistent,
                    keepalive=5,
                    **login,
                ) as client:
                    await client.subscribe(topic, qos=1)
                    await client.subscribe(marker, qos=1)  # after it: once here, both are
                    async for message in client.messages:
                        received._add(message)
            except aiomqtt.MqttError:
                if not persistent:
                    raise
                await asyncio.sleep(0.05)

    # Subscribed once a message we publish ourselves comes back (retained ones may be none).
    marker = f"tests/subscribed/{uuid.uuid4().hex}"
    task = asyncio.create_task(collect())
    async with aiomqtt.Client("127.0.0.1", port, **login) as probe:
        async with asyncio.timeout(WAIT_S):
            while not received.on(marker):
                await probe.publish(marker, b"1", qos=1)
                await asyncio.sleep(0.05)
    try:
        yield received
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
