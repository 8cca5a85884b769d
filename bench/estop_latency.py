"""Software-stop latency: POST /estop leaving the client → robot stopped AND valve closed.

A trial sends POST /estop and ends when the robot simulator has received
`stop` and the glue simulator has received the valve-close write (both stamp
time.time() on arrival; the valve register is then checked to read closed).
The latency is the later of the two stamps minus the moment just before the
request left the client. Then the cell is reset to IDLE for the next trial.

Who runs where: the server (the production app under uvicorn) in this
process's main loop, so the benchmark can set each condition up directly; the
robot and glue simulators and the HTTP client (kept alive, as an HMI holds
its connection) in a process of their own (bench/stop_witness.py), as
separate devices and HMIs are; and for the WebSocket condition, the 1000
clients in another process (bench/ws_crowd.py). The simulated camera
renders in the server, as in the default run.

Where the time goes, per trial (p50 and p99 columns): `to_server` from the
request leaving the client to its arrival at the app's outermost layer (the
client's send, the kernel, the server's loop getting to it); `in_server` from
there to the halt commands being created (HTTP parsing, routing, the access
gate, the handler); `to_devices` from there to the later of the two device
stamps (the two protocol clients, the kernel, the simulators' parsing).
`to_sockets` is the server's whole share, from the request's arrival at the
app to the later of the robot's `stop` and the valve-close frame being
handed to their sockets (the transport's write, which sends at once).
`to_sockets_line_free` is the same over the stops that found the
dispenser's line free; the others (`line_busy_stops`) found an exchange
under way, and Modbus RTU writes the close only once its reply is in (on
RS-485 at 115200 baud an exchange takes about 2 ms, whatever the server does).
`answer` is the POST /estop round trip as the client sees it: until it has
read the answer, which the server gives once both devices answered, the run
is cancelled and the stop is on record (its journal commit, fsync included).

Conditions, each with --trials e-stops (default 500):
- idle: the cell in IDLE, nothing running;
- trajectory running: a spraying run started, the stop sent at a random moment in
  its first 0.3 s on the spray path (the valve open, the robot drawing the first
  bead). Not at once: a stop sent as the run reached the path always arrived
  while the run's own flow and valve-open commands were on the dispenser's line
  (7 stops in 10 found it busy; an operator's stop lands at any moment, and then
  finds the line busy about 1 time in 100: the monitor's poll every 0.1 s);
- event queue full: the request lane filled to event_queue_size with requests
  just before the stop is sent (the worker is still draining them);
- 1000 WebSocket clients: 1000 live /ws clients reading every message, the cell IDLE;
- vision operation running: a robot calibration started (capture, marker
  detection on a 1920×1080 frame in a worker thread), the stop sent at a
  random moment in its first 60 ms.

`--pin` (the headline figure, as a cell's controller has its own core): the
server, with every thread it starts, on one core; the witness and the crowd on
the other(s). Unpinned, the simulators, the HMI and 1000 Python clients take
turns with the server on two cores, and the figure measures them as much as the
server. Pinned, the crowd also runs at a lower priority (nice 10) than the
witness beside it: the simulators stand for devices of their own, which 1000
dashboards do not slow down (starved, the glue simulator took up to 5 ms to
answer a status poll, and a stop arriving then waited for that answer: Modbus
RTU has one exchange on the line at a time). The result file says which
(`pinned`); `--name` keeps a pinned and an unpinned run apart.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import os
import random
import subprocess
import sys
import tempfile
import time
from asyncio.selector_events import _SelectorSocketTransport
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

import uvicorn
from starlette.types import ASGIApp, Receive, Scope, Send

from bench.report import emit, percentiles_ms
from bench.ws_fanout import pinning
from server.__main__ import uvicorn_options
from server.bootstrap.app import create_app
from server.bootstrap.cell import Cell
from server.common.errors import EventQueueFull
from server.core.machine.events import StartPayload
from server.core.machine.transitions import Event, State
from server.core.worker import stop as stop_service
from server.core.worker.devices import CellDevices, HaltReport
from server.core.worker.worker import Worker
from server.drivers.glue_registers import VALVE_COMMAND
from server.settings.model import Settings
from tests.serving import free_port

ROOT = Path(__file__).resolve().parents[1]
SPRAY_DEMO = StartPayload(contour_matching=False, workpiece_id="demo")
CONDITIONS = (
    "idle",
    "trajectory running",
    "event queue full",
    "1000 WebSocket clients",
    "vision operation running",
)


class StopWitness:
    """The simulators' and the HMI's process (bench/stop_witness.py)."""

    def __init__(self, cores: set[int] | None = None) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-m", "bench.stop_witness"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            cwd=ROOT,
        )
        keep_to(self.process.pid, cores)  # at once: it starts no thread before its imports
        assert self.process.stdout is not None and self.process.stdin is not None
        self.stdin, self.stdout = self.process.stdin, self.process.stdout
        _, robot, _, glue = self.stdout.readline().split()
        self.robot_port, self.glue_port = int(robot), int(glue)

    def tell(self, line: str) -> list[str]:
        self.stdin.write(line + "\n")
        self.stdin.flush()
        return self.stdout.readline().split()

    def estop_once(self) -> tuple[float, float, float]:
        """POST /estop from the witness: (seconds until both devices had it, time sent,
        seconds until the client had read the answer)."""
        answer = self.tell("fire")
        if answer[0] != "stopped":
            raise RuntimeError(f"the e-stop failed: {' '.join(answer)}")
        assert answer[2] == "True", "the valve does not read closed after the stop"
        return float(answer[1]), float(answer[3]), float(answer[4])

    def close(self) -> None:
        self.stdin.close()
        self.process.wait(10)


class StopStages:
    """Where a stop's time goes inside the server: when its request reached the
    app (outermost ASGI layer) and when the halt commands were created."""

    def __init__(self, app: ASGIApp, cell: Cell) -> None:
        self.app = app
        self.cell = cell
        self.clear()

    def clear(self) -> None:
        self.arrived: float | None = None
        self.halted: float | None = None
        # Whether the dispenser's line had an exchange under way when the halt was made.
        self.line_busy = False
        self.written: dict[str, float] = {}

    def watch_sockets(self, robot_port: int, glue_port: int) -> None:
        """Stamp the moment each stop frame is handed to its device's socket."""
        close = b"\x01\x06" + VALVE_COMMAND.address.to_bytes(2, "big") + b"\x00\x00"
        frames = {robot_port: ("robot", b'"stop"'), glue_port: ("glue", close)}
        write = _SelectorSocketTransport.write
        stages = self

        def stamped(transport: _SelectorSocketTransport, data: Any) -> None:
            peer = transport.get_extra_info("peername")
            device = frames.get(peer[1]) if peer else None
            fresh = device is not None and device[0] not in stages.written
            if fresh and device is not None and device[1] in bytes(data):
                stages.written[device[0]] = time.time()
            write(transport, data)

        _SelectorSocketTransport.write = stamped  # type: ignore[method-assign]

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and scope["path"] == "/estop":
            self.arrived = time.time()
        await self.app(scope, receive, send)

    def watch_halts(self) -> None:
        devices = self.cell.devices
        made = stop_service.halt_at_once

        def stamped(on: CellDevices, timeout: float) -> asyncio.Future[HaltReport]:
            if self.halted is None:
                self.halted = time.time()
                self.line_busy = bool(getattr(devices.glue, "line_busy", False))
            return made(on, timeout)

        stop_service.halt_at_once = stamped  # type: ignore[assignment]


async def wait_state(worker: Worker, *states: State) -> None:
    while worker.ctx.state not in states:
        await asyncio.sleep(0.001)


async def to_idle(worker: Worker) -> None:
    await wait_state(worker, State.IDLE, State.ERROR)
    while worker.ctx.state is State.ERROR:
        await worker.request(Event.RESET_REQUESTED, source="bench")
    await wait_state(worker, State.IDLE)


async def start_spraying(worker: Worker, rng: random.Random) -> None:
    outcome = await worker.request(Event.START_REQUESTED, source="bench", payload=SPRAY_DEMO)
    assert outcome.accepted, outcome.message
    # Past the approach move: on the spray path, the valve opening.
    while (running := worker.ctx.operation) is None or running.progress.get("waypoint", 0) < 2:
        await asyncio.sleep(0.001)
    await asyncio.sleep(rng.uniform(0.0, 0.3))
    progress = running.progress
    on_path = progress.get("waypoint", 0) < progress.get("total", 0) - 1  # the lift not reached
    assert worker.ctx.state is State.EXECUTING_TRAJECTORY and on_path, "the spray ended first"


async def fill_queue(worker: Worker) -> None:
    """Requests the cell will refuse in IDLE, until the bounded lane refuses more."""
    with contextlib.suppress(EventQueueFull):
        while True:
            worker.submit(Event.PAUSE_REQUESTED, source="bench")


async def start_vision(worker: Worker, rng: random.Random) -> None:
    outcome = await worker.request(Event.CALIBRATE_ROBOT_REQUESTED, source="bench")
    assert outcome.accepted, outcome.message
    await asyncio.sleep(rng.uniform(0.0, 0.06))


def keep_to(pid: int, cores: set[int] | None, nice: int = 0) -> None:
    """Keep every thread of process `pid` (0: this one) to `cores`, at niceness `nice`
    (None: no pinning). Threads started later inherit it from the thread that starts them.

    Every thread, not the process's first alone: on Linux affinity and niceness
    are a thread's, and numpy and OpenCV start threads of their own when imported.
    """
    if cores is None:
        return
    for thread in os.listdir(f"/proc/{pid or os.getpid()}/task"):
        with contextlib.suppress(ProcessLookupError):  # a thread that ended meanwhile
            os.sched_setaffinity(int(thread), cores)
            if nice:
                os.setpriority(os.PRIO_PROCESS, int(thread), nice)


CROWD_NICE = 10  # pinned: the simulated devices, on the crowd's core, are served first


@contextlib.asynccontextmanager
async def ws_crowd(
    port: int, token: str, clients: int, cores: set[int] | None = None
) -> AsyncIterator[None]:
    """`clients` live /ws connections, in a process of their own."""
    crowd = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "bench.ws_crowd",
        "--url",
        f"ws://127.0.0.1:{port}/ws",
        "--clients",
        str(clients),
        stdin=asyncio.subprocess.PIPE,
        stdout=asyncio.subprocess.PIPE,
        env={**os.environ, "GLUE_BENCH_TOKEN": token},
        cwd=ROOT,
    )
    keep_to(crowd.pid, cores, nice=CROWD_NICE)
    assert crowd.stdout is not None and crowd.stdin is not None
    line = (await crowd.stdout.readline()).decode()
    if not line.startswith("connected"):
        crowd.kill()
        raise RuntimeError(f"the WebSocket crowd did not connect: {line!r}")
    try:
        yield
    finally:
        crowd.stdin.close()
        await asyncio.wait_for(crowd.wait(), 60)


async def trials_in(
    condition: str,
    trials: int,
    worker: Worker,
    witness: StopWitness,
    stages: StopStages,
    rng: random.Random,
) -> dict[str, list[float]]:
    prepare: dict[str, Callable[[], Awaitable[None]]] = {
        "trajectory running": lambda: start_spraying(worker, rng),
        "event queue full": lambda: fill_queue(worker),
        "vision operation running": lambda: start_vision(worker, rng),
    }
    samples: dict[str, list[float]] = {
        "total": [],
        "to_server": [],
        "in_server": [],
        "to_devices": [],
        "to_sockets": [],
        "to_sockets_line_free": [],
        "answer": [],
    }
    for _ in range(trials):
        await to_idle(worker)
        if condition in prepare:
            await prepare[condition]()
        stages.clear()
        total, sent, answered = await asyncio.to_thread(witness.estop_once)
        samples["total"].append(total)
        samples["answer"].append(answered)
        if stages.arrived is not None and stages.halted is not None:
            samples["to_server"].append(stages.arrived - sent)
            samples["in_server"].append(stages.halted - stages.arrived)
            samples["to_devices"].append(sent + total - stages.halted)
            if len(stages.written) == 2:
                to_sockets = max(stages.written.values()) - stages.arrived
                samples["to_sockets"].append(to_sockets)
                if not stages.line_busy:
                    samples["to_sockets_line_free"].append(to_sockets)
    await to_idle(worker)
    return samples


async def run(
    trials: int,
    queue_size: int,
    ws_clients: int,
    others: set[int] | None = None,
    recording: bool = True,
) -> list[dict[str, Any]]:
    """The conditions' rows; `others`: the cores of the witness and the crowd, when pinned.

    The cell's data (a journal of some 50 MB after a full run) goes with the run.
    """
    with tempfile.TemporaryDirectory(prefix="bench-cell-") as data:
        return await run_in(Path(data), trials, queue_size, ws_clients, others, recording)


async def run_in(
    data: Path,
    trials: int,
    queue_size: int,
    ws_clients: int,
    others: set[int] | None,
    recording: bool = True,
) -> list[dict[str, Any]]:
    """`run` with the cell's data in `data`."""
    witness = await asyncio.to_thread(StopWitness, others)
    settings = Settings(
        robot_ip="127.0.0.1",
        robot_port=witness.robot_port,
        glue_controller_port=f"tcp://127.0.0.1:{witness.glue_port}",
        event_queue_size=queue_size,
        max_broadcast_clients=ws_clients + 10,
        max_broadcast_clients_per_token=ws_clients + 10,  # the crowd shares one token
        # the crowd's connections all come from 127.0.0.1
        http_max_connections=ws_clients + 100,
        http_max_connections_per_address=ws_clients + 100,
        emergency_stop_timeout=1.0,
        data_path=data,
        run_recording=recording,
    )
    cell = Cell(settings)
    port = free_port()
    app = create_app(cell=cell, tune_process=True)  # as python -m server does
    stages = StopStages(app, cell)
    server = uvicorn.Server(
        uvicorn.Config(
            stages,
            host="127.0.0.1",
            port=port,
            log_level="error",
            **uvicorn_options(settings),
        )
    )
    serving = asyncio.create_task(server.serve())
    while not server.started:
        await asyncio.sleep(0.01)
    token = (settings.data_path / "admin.token").read_text().strip()
    assert await asyncio.to_thread(witness.tell, f"server http://127.0.0.1:{port} {token}")
    assert cell.worker is not None
    await wait_state(cell.worker, State.IDLE)
    stages.watch_halts()
    stages.watch_sockets(witness.robot_port, witness.glue_port)
    rng = random.Random(20261122)
    rows = []
    for condition in CONDITIONS:
        label = condition.replace("1000", str(ws_clients))
        crowd = ws_crowd(port, token, ws_clients, others) if "WebSocket" in condition else None
        async with crowd or contextlib.nullcontext():
            samples = await trials_in(condition, trials, cell.worker, witness, stages, rng)
        stage_p50 = {f"{k}_p50_ms": percentiles_ms(v)["p50_ms"] for k, v in samples.items()}
        stage_p99 = {f"{k}_p99_ms": percentiles_ms(v)["p99_ms"] for k, v in samples.items()}
        busy = len(samples["to_sockets"]) - len(samples["to_sockets_line_free"])
        rows.append(
            {
                "condition": label,
                **percentiles_ms(samples["total"]),
                "target_p99_ms": 10.0,
                "line_busy_stops": busy,
                **{k: v for k, v in stage_p50.items() if not k.startswith("total")},
                **{k: v for k, v in stage_p99.items() if not k.startswith("total")},
            }
        )
    server.should_exit = True
    await serving
    await asyncio.to_thread(witness.close)
    return rows


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--trials", type=int, default=500, help="e-stops per condition")
    parser.add_argument("--queue-size", type=int, default=1000)
    parser.add_argument("--ws-clients", type=int, default=1000)
    parser.add_argument(
        "--pin",
        action="store_true",
        help="the server on one core, the witness and the crowd on the others",
    )
    parser.add_argument("--name", default="estop_latency", help="the result file's name")
    parser.add_argument(
        "--no-recording",
        action="store_true",
        help="run_recording off: the flight recorder's share of the stop, against a default run",
    )
    args = parser.parse_args(argv)
    logging.disable(logging.ERROR)  # every e-stop logs a fault; not what is measured
    cores = pinning(args.pin)
    keep_to(0, cores[0] if cores is not None else None)  # before the server starts any thread
    others = cores[1] if cores is not None else None
    recording = not args.no_recording
    rows = asyncio.run(run(args.trials, args.queue_size, args.ws_clients, others, recording))
    pinned: Any = (
        {"server_cores": sorted(cores[0]), "other_cores": sorted(cores[1])}
        if cores
        else "no: the server, the witness and the crowd share every core"
    )
    extra = {
        "trials": args.trials,
        "queue_size": args.queue_size,
        "pinned": pinned,
        "run_recording": recording,
    }
    emit(args.name, rows, {**extra, "ws_clients": args.ws_clients})
    return rows


if __name__ == "__main__":
    main()
