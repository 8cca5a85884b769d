"""A line of cells on one machine: Debian's mosquitto, N cells and the line view, as processes.

    python -m server.line.demo            (what `make line` runs)

Each cell is a separate `python -m server` on the simulated cell, with its own port
(8001, 8002, ...), data directory (data/line/cell-N) and cell id (cell-N), told
where the broker is by GLUE_APP_MQTT_URL; the line view (`server.line.view`) reads
them all from the broker's WebSocket listener. Everything listens on loopback
unless --host says otherwise. Ctrl-C (or SIGTERM) stops every process together,
and so does any one of them exiting on its own: a line half up is not a demo.

A first start commissions each simulated cell (calibrations, CPU-bound): minutes on
a small machine with three at once; the data directories keep that for next time.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import FrameType

import httpx

from server.line.broker import DEMO_PASSWORDS, BrokerNotStarted, BrokerPorts, start_broker

STOP_GRACE_S = 15.0
START_TIMEOUT_S = 900.0


@dataclass
class Child:
    """One process of the line, named for the messages."""

    name: str
    process: subprocess.Popen[bytes]
    log: Path


class LineFailed(RuntimeError):
    """A process of the line did not start, or exited while the line ran."""


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m server.line.demo",
        description="Start mosquitto, a line of simulated cells and the line view; "
        "Ctrl-C stops them all.",
    )
    parser.add_argument("--host", default="127.0.0.1", help="address of every listener")
    parser.add_argument("--cells", type=int, default=3, choices=range(1, 10), metavar="1-9")
    parser.add_argument("--first-port", type=int, default=8001, help="cell-1's HTTP port")
    parser.add_argument("--mqtt-port", type=int, default=1883, help="the broker's MQTT port")
    parser.add_argument("--ws-port", type=int, default=9001, help="the broker's WebSocket port")
    parser.add_argument("--view-port", type=int, default=8080, help="the line view's HTTP port")
    parser.add_argument(
        "--data-dir", type=Path, default=Path("data/line"), help="cell-N/ and the broker's files"
    )
    return parser.parse_args(argv)


def cell_environment(cell_id: str, broker: BrokerPorts) -> dict[str, str]:
    """The environment of one cell: the caller's, with its id and the line's broker, where
    it signs in as the demo's `cell` user (server/line/broker.py)."""
    return {
        **os.environ,
        "GLUE_APP_CELL_ID": cell_id,
        "GLUE_APP_MQTT_URL": broker.mqtt_url,
        "GLUE_APP_MQTT_USERNAME": "cell",
        "GLUE_APP_MQTT_PASSWORD": DEMO_PASSWORDS["cell"],
    }


def _spawn(name: str, argv: list[str], log: Path, env: dict[str, str] | None = None) -> Child:
    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("wb") as output:
        process = subprocess.Popen(argv, stdout=output, stderr=subprocess.STDOUT, env=env)
    say(f"started {name} (pid {process.pid}), log {log}")
    return Child(name, process, log)


def say(text: str) -> None:
    print(f"line: {text}", flush=True)


def wait_http(child: Child, url: str, deadline: float) -> None:
    """Until `url` answers 200; LineFailed if the process exits or the deadline passes.

    One client for every poll: a new one per poll would load the system's CA
    certificates again each time (tens of milliseconds of CPU) while the cells start."""
    with httpx.Client(timeout=2) as client:
        while True:
            if child.process.poll() is not None:
                tail = child.log.read_text(errors="replace")[-1500:]
                raise LineFailed(f"{child.name} exited with {child.process.returncode}:\n{tail}")
            try:
                if client.get(url).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline:
                raise LineFailed(f"{child.name} did not answer {url} in time (log {child.log})")
            time.sleep(0.5)


def stop_all(children: list[Child]) -> None:
    """SIGTERM every process (the cells shut down cleanly), then kill what lingers."""
    for child in reversed(children):
        if child.process.poll() is None:
            child.process.terminate()
    deadline = time.monotonic() + STOP_GRACE_S
    for child in reversed(children):
        try:
            child.process.wait(max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            child.process.kill()
            child.process.wait()
        say(f"stopped {child.name} (exit {child.process.returncode})")


@contextlib.contextmanager
def running_line(args: argparse.Namespace) -> Iterator[list[Child]]:
    """Start the broker, the cells and the line view; stop them all on the way out."""
    children: list[Child] = []
    data: Path = args.data_dir.resolve()
    broker = BrokerPorts(args.host, args.mqtt_port, args.ws_port)
    try:
        try:
            process = start_broker(broker, data / "mosquitto")
        except BrokerNotStarted as error:
            log = data / "mosquitto" / "mosquitto.log"
            raise LineFailed(f"mosquitto: {error} (log {log})") from None
        children.append(Child("mosquitto", process, data / "mosquitto" / "mosquitto.log"))
        say(f"started mosquitto (pid {process.pid}): {broker.mqtt_url}, {broker.websocket_url}")
        cells = []
        for n in range(1, args.cells + 1):
            cell_id, port, directory = f"cell-{n}", args.first_port + n - 1, data / f"cell-{n}"
            argv = [sys.executable, "-m", "server", "--host", args.host, "--port", str(port)]
            argv += ["--data-dir", str(directory)]
            env = cell_environment(cell_id, broker)
            child = _spawn(cell_id, argv, directory / "server.log", env)
            children.append(child)
            cells.append((child, f"http://{args.host}:{port}"))
        view_argv = [sys.executable, "-m", "server.line.view", "--host", args.host]
        view_argv += ["--port", str(args.view_port), "--broker-ws", broker.websocket_url]
        view = _spawn("line view", view_argv, data / "line-view.log")
        children.append(view)
        deadline = time.monotonic() + START_TIMEOUT_S
        view_url = f"http://{args.host}:{args.view_port}/"
        wait_http(view, view_url, deadline)
        for child, url in cells:
            wait_http(child, f"{url}/health", deadline)
            say(f"{child.name} up: {url} (token in {data / child.name / 'admin.token'})")
        say(
            f"broker users (demo passwords, in server/line/broker.py): cell, operator, "
            f"line-view; e.g. gluectl line --broker {broker.login_url('line-view')}"
        )
        say(f"ready: line view {view_url} · broker {broker.mqtt_url} · Ctrl-C stops all")
        yield children
    finally:
        stop_all(children)


def watch(children: list[Child]) -> None:
    """Until one of the processes exits on its own (LineFailed) or Ctrl-C."""
    while True:
        for child in children:
            if child.process.poll() is not None:
                raise LineFailed(f"{child.name} exited with {child.process.returncode}")
        time.sleep(0.5)


def _interrupt(signum: int, _frame: FrameType | None) -> None:
    raise KeyboardInterrupt(signal.Signals(signum).name)


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    signal.signal(signal.SIGTERM, _interrupt)  # a service manager's stop is a Ctrl-C
    try:
        with running_line(args) as children:
            watch(children)
    except KeyboardInterrupt:
        say("stopped")
        return 0
    except LineFailed as error:
        say(f"failed: {error}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
