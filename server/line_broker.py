"""Debian's mosquitto as a child process: the broker of a line of cells on one machine.

The line demo (`server/line_demo.py`) and the tests run the same broker the plant
would, from a configuration written here: an MQTT listener for the cells and
`gluectl line`, and a WebSocket listener for the line view in a browser (Debian's
mosquitto 2.0 has WebSockets built in). Anonymous clients are allowed, as a lab
broker: a plant's broker has its own users and ACLs (docs/plant-integration.md).
"""

from __future__ import annotations

import shutil
import socket
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

MOSQUITTO_PATHS = ("/usr/sbin/mosquitto",)
INSTALL_HINT = "install Debian's mosquitto (`make mosquitto`, or apt-get install mosquitto)"


class BrokerNotStarted(RuntimeError):
    """mosquitto is missing, exited, or did not open its listeners."""


def mosquitto_binary() -> str:
    """The mosquitto executable (Debian installs it in /usr/sbin, often not on PATH)."""
    found = shutil.which("mosquitto") or next(
        (path for path in MOSQUITTO_PATHS if Path(path).is_file()), None
    )
    if found is None:
        raise BrokerNotStarted(f"mosquitto is not installed: {INSTALL_HINT}")
    return found


@dataclass(frozen=True)
class BrokerPorts:
    """Where the broker listens: MQTT for the cells, WebSocket for browsers."""

    host: str
    mqtt: int
    websocket: int

    @property
    def mqtt_url(self) -> str:
        return f"mqtt://{self.host}:{self.mqtt}"

    @property
    def websocket_url(self) -> str:
        return f"ws://{self.host}:{self.websocket}"


def broker_config(ports: BrokerPorts) -> str:
    """mosquitto.conf for a line: two listeners on `ports.host`, no persistence file
    (the cells republish their retained topics when they connect)."""
    return (
        "# Written by server/line_broker.py for a line of cells on one machine.\n"
        "per_listener_settings false\n"
        "allow_anonymous true\n"
        "persistence false\n"
        "log_dest stdout\n"
        "log_type error\nlog_type warning\nlog_type notice\n"
        f"listener {ports.mqtt} {ports.host}\n"
        "protocol mqtt\n"
        f"listener {ports.websocket} {ports.host}\n"
        "protocol websockets\n"
    )


def wait_listening(host: str, port: int, process: subprocess.Popen[bytes], timeout: float) -> None:
    """Until `host:port` accepts a connection; BrokerNotStarted if the process exits first."""
    deadline = time.monotonic() + timeout
    while True:
        if process.poll() is not None:
            raise BrokerNotStarted(f"mosquitto exited with {process.returncode}")
        try:
            with socket.create_connection((host, port), timeout=1):
                return
        except OSError:
            if time.monotonic() > deadline:
                raise BrokerNotStarted(f"mosquitto did not listen on {host}:{port}") from None
            time.sleep(0.05)


def start_broker(
    ports: BrokerPorts, directory: Path, log_path: Path | None = None, timeout: float = 30.0
) -> subprocess.Popen[bytes]:
    """Write `directory/mosquitto.conf`, start mosquitto on it, return once both
    listeners accept connections. The caller stops the process."""
    directory.mkdir(parents=True, exist_ok=True)
    config = directory / "mosquitto.conf"
    config.write_text(broker_config(ports))
    log = (log_path or directory / "mosquitto.log").open("wb")
    process = subprocess.Popen(
        [mosquitto_binary(), "-c", str(config)], stdout=log, stderr=subprocess.STDOUT
    )
    log.close()  # the child holds its own descriptor
    try:
        wait_listening(ports.host, ports.mqtt, process, timeout)
        wait_listening(ports.host, ports.websocket, process, timeout)
    except BrokerNotStarted:
        process.kill()
        process.wait()
        raise
    return process
