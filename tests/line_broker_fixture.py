"""Debian's mosquitto on free loopback ports for a test, started as the line demo starts it
(server/line/broker.py). Missing mosquitto fails, never skips: `make test` installs it."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

from server.line.broker import BrokerPorts, start_broker
from tests.processes import stop
from tests.serving import free_port


@contextlib.contextmanager
def running_broker(directory: Path) -> Iterator[BrokerPorts]:
    ports = BrokerPorts("127.0.0.1", free_port(), free_port())
    process = start_broker(ports, directory)
    try:
        yield ports
    finally:
        stop(process)  # type: ignore[arg-type]  # stop() reads only poll/send_signal/wait
