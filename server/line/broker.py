"""Debian's mosquitto as a child process: the broker of a line of cells on one machine.

The line demo (`server/line/demo.py`) and the tests run the same broker the plant
would, from a configuration written here: an MQTT listener for the cells and
`gluectl line`, and a WebSocket listener for the line view in a browser (Debian's
mosquitto 2.0 has WebSockets built in).

It has the shipped broker's access control (deploy/mosquitto/acl): on the MQTT
listener anonymous clients are refused, only the `cell` user reads commands, an
`operator` sends them and reads the answers, `line-view` reads the state only. The
password file is made at each start in the broker's directory, with the demo
passwords of DEMO_PASSWORDS: known to anyone who reads this file, so a demo broker is
for loopback or a lab, never a plant (docs/plant-integration.md, "The broker"). The
WebSocket listener, for the line view's page in a browser, which has no password to
give, lets an anonymous client read what `line-view` may (the state), nothing more.
"""

from __future__ import annotations

import getpass
import shutil
import socket
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

MOSQUITTO_PATHS = ("/usr/sbin/mosquitto",)
ACL_FILE = Path(__file__).resolve().parents[2] / "deploy" / "mosquitto" / "acl"
# The demo's users and their passwords: public, for a broker on loopback or in a lab.
DEMO_PASSWORDS = {
    "cell": "cell-demo-password",
    "operator": "operator-demo-password",
    "line-view": "line-view-demo-password",
    "scada": "scada-demo-password",
}
ANONYMOUS_STATE_READER = (
    "# The browser's listener: anonymous may read the state only.\ntopic read glue/+/+\n"
)
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

    def login_url(self, user: str) -> str:
        """`mqtt://user:password@host:port` for one of the demo users (gluectl line)."""
        return f"mqtt://{user}:{DEMO_PASSWORDS[user]}@{self.host}:{self.mqtt}"

    @property
    def websocket_url(self) -> str:
        return f"ws://{self.host}:{self.websocket}"


def broker_config(ports: BrokerPorts, directory: Path) -> str:
    """mosquitto.conf for a line: two listeners on `ports.host`, each with the password
    file and ACL in `directory`, no persistence file (the cells republish their retained
    topics when they connect)."""
    return (
        "# Written by server/line/broker.py for a line of cells on one machine.\n"
        "per_listener_settings true\n"
        # Started as root, mosquitto would drop to its own user, who cannot read the
        # password file (0600) in this directory; as anyone else this line is ignored.
        f"user {getpass.getuser()}\n"
        "persistence false\n"
        "log_dest stdout\n"
        "log_type error\nlog_type warning\nlog_type notice\n"
        f"listener {ports.mqtt} {ports.host}\n"
        "protocol mqtt\n"
        "allow_anonymous false\n"
        f"password_file {directory / 'passwd'}\n"
        f"acl_file {directory / 'acl'}\n"
        f"listener {ports.websocket} {ports.host}\n"
        "protocol websockets\n"
        "allow_anonymous true\n"
        f"password_file {directory / 'passwd'}\n"
        f"acl_file {directory / 'websocket.acl'}\n"
    )


def shipped_acl() -> str:
    """deploy/mosquitto/acl: the one ACL the demo, the tests and docker-compose use."""
    try:
        return ACL_FILE.read_text(encoding="utf-8")
    except OSError as error:
        raise BrokerNotStarted(f"the broker's ACL is missing: {error}") from None


def write_password_file(path: Path, passwords: dict[str, str]) -> None:
    """A mosquitto password file of `passwords` (user: password), made by mosquitto_passwd
    (salted hashes, mode 0600); BrokerNotStarted if it cannot be made."""
    tool = shutil.which("mosquitto_passwd") or "/usr/bin/mosquitto_passwd"
    path.unlink(missing_ok=True)
    path.touch(mode=0o600)
    for user, password in passwords.items():
        try:
            subprocess.run([tool, "-b", str(path), user, password], check=True, capture_output=True)
        except (OSError, subprocess.CalledProcessError) as error:
            raise BrokerNotStarted(f"mosquitto_passwd failed: {error}; {INSTALL_HINT}") from None


def write_access_files(directory: Path, passwords: dict[str, str] = DEMO_PASSWORDS) -> None:
    """The password file and the ACLs a broker in `directory` reads."""
    acl = shipped_acl()
    (directory / "acl").write_text(acl)
    (directory / "websocket.acl").write_text(ANONYMOUS_STATE_READER + acl)
    write_password_file(directory / "passwd", passwords)


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
    write_access_files(directory)
    config.write_text(broker_config(ports, directory))
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
