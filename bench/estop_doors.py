"""The stop through every door, side by side: HTTP, MQTT and OPC UA, quiet and flooded.

A trial sends one e-stop through one door and measures the **device stop**: from
just before the stop was handed to the door's client to the later of the robot
receiving `stop` and the dispenser receiving the valve-close write (the
simulators' own stamps, as `bench.estop_latency` takes them). `written_p50_ms` and
`written_p99_ms` measure the same stop from when the doors' client handed its bytes
to the kernel: what the client's own loop and outgoing queue held it for is not in
them (bench/door_client.py: `StopWrites`). That time is split in two at the moment
the server began the halt (`EmergencyStops.last_halted_at`, both frames written
straight after): `server_*` from the client's bytes to the halt (the kernel's
delivery, the wait for a core, the door), `devices_*` from the halt to the later
device stamp (the two frames written, and the simulators' process waking to read
them, on the same cores).

Three conditions per door, `--mqtt-flood` / `--opcua-flood` / `--http-flood` pause
commands ahead of the stop when flooded:
- quiet: the stop alone;
- flooded by another client: a second client process (a runaway script beside the
  HMI) has begun its flood when the HMI's client sends the stop on its own
  connection; what the stop waits for is the server's (and the broker's) doing;
- behind its own client's pauses: the flood on the stop's own connection (MQTT: the
  same client, so the broker delivers the stop after them, as MQTT's ordering asks;
  OPC UA: the same session, the calls all on their way before the first is answered;
  HTTP: a pool of 64 connections of the same client, the stop on the HMI's own
  kept-alive one), so the stop also waits for its own client and the ordered stream.
The pauses are refused in IDLE and in ERROR, so each costs the door and the worker
their whole path and changes nothing. After each trial the cell is reset to IDLE.

Who runs where: the server (the production app under uvicorn, MQTT commands and
OPC UA on) in this process's loop; Debian's mosquitto; the robot and glue
simulators in a process of their own (bench/stop_witness.py); the three doors'
clients in another, the other client's flood in a third (bench/door_client.py).
Every door's conditions alternate trial by trial, so the machine's moods fall on all
of them alike.

Run: `python -m bench.estop_doors` (`--trials 30` per door and condition by
default; `--doors http` measures one door). No timing is promised: on a shared
machine the figures measure the machine as much as the server.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import httpx
import uvicorn

from bench.door_client import HTTP_POOL
from bench.estop_latency import StopWitness, to_idle, wait_state
from bench.report import emit, percentiles_ms
from server.__main__ import uvicorn_options
from server.bootstrap.app import create_app
from server.bootstrap.cell import Cell
from server.core.machine.transitions import State
from server.settings.model import Settings
from tests.mosquitto import mosquitto
from tests.processes import ROOT
from tests.serving import free_port

CELL_ID = "cell-bench"
DOORS = ("http", "mqtt", "opcua")
QUIET = "quiet"
OTHER = "flooded by another client ({flood} pauses)"
SAME = "behind {flood} pauses of its own client"
CONDITIONS = (QUIET, OTHER, SAME)


class DoorClient:
    """The doors' clients' process (bench/door_client.py)."""

    def __init__(self, http_url: str, mqtt_port: int, opcua_url: str, token: str) -> None:
        self.process = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "bench.door_client",
                http_url,
                str(mqtt_port),
                opcua_url,
                CELL_ID,
            ],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            cwd=ROOT,
            env={**os.environ, "GLUE_BENCH_TOKEN": token},
        )
        assert self.process.stdout is not None and self.process.stdin is not None
        self.stdin, self.stdout = self.process.stdin, self.process.stdout
        line = self.stdout.readline()
        if line.strip() != "ready":
            raise RuntimeError(f"the door client did not start: {line!r}")

    def stop(self, door: str, flood: int) -> tuple[float, float]:
        """Send one stop behind `flood` commands: when it was handed to the door's client,
        and when its bytes were handed to the kernel."""
        self.stdin.write(f"stop {door} {flood}\n")
        self.stdin.flush()
        words = self.stdout.readline().split()
        if len(words) != 3 or words[0] != "sent":
            raise RuntimeError(f"the {door} stop failed: {words}")
        return float(words[1]), float(words[2])

    def flood(self, door: str, count: int) -> None:
        """Begin a flood of `count` pauses through `door`; return once it is on its way."""
        self._ask(f"flood {door} {count}", "begun")

    def finish(self) -> None:
        """Wait until the flood is answered."""
        self._ask("finish", "done")

    def _ask(self, line: str, answer: str) -> None:
        self.stdin.write(line + "\n")
        self.stdin.flush()
        if (got := self.stdout.readline().strip()) != answer:
            raise RuntimeError(f"the door client answered {got!r} to {line!r}")

    def close(self) -> None:
        self.stdin.close()
        self.process.wait(30)


async def run(args: argparse.Namespace, data: Path) -> list[dict[str, Any]]:
    floods = {"http": args.http_flood, "mqtt": args.mqtt_flood, "opcua": args.opcua_flood}
    witness = await asyncio.to_thread(StopWitness)
    with mosquitto(data / "broker") as broker:
        opcua_port = free_port()
        settings = Settings(
            robot_ip="127.0.0.1",
            robot_port=witness.robot_port,
            glue_controller_port=f"tcp://127.0.0.1:{witness.glue_port}",
            emergency_stop_timeout=1.0,
            data_path=data / "cell",
            cell_id=CELL_ID,
            mqtt_commands=True,
            opcua_endpoint=f"opc.tcp://127.0.0.1:{opcua_port}",
            event_queue_size=max(1000, 2 * max(floods.values())),
            # The HMI and the other client stand for two hosts, but here share one
            # address: each has its own share of connections, as two hosts would.
            http_max_connections_per_address=4 * HTTP_POOL,
            **broker.cell_login,
        )
        cell = Cell(settings)
        port = free_port()
        server = uvicorn.Server(
            uvicorn.Config(
                # as python -m server runs: its collector tuned (server/bootstrap/latency.py),
                # its HTTP protocol the guarded one (server/api/connection_guard.py)
                create_app(cell=cell, tune_process=True),
                host="127.0.0.1",
                port=port,
                log_level="error",
                **uvicorn_options(settings),
            )
        )
        serving = asyncio.create_task(server.serve())
        while not server.started:
            await asyncio.sleep(0.01)
        assert cell.worker is not None
        await wait_state(cell.worker, State.IDLE)
        admin = (settings.data_path / "admin.token").read_text().strip()
        url = f"http://127.0.0.1:{port}"
        async with httpx.AsyncClient(
            base_url=url, headers={"Authorization": f"Bearer {admin}"}
        ) as http:
            made = await http.post("/tokens", json={"name": "bench", "role": "operator"})
            token = made.json()["token"]
            while not (await http.get("/health")).json()["mqtt"]["connected"]:
                await asyncio.sleep(0.05)
        opcua_url = f"opc.tcp://127.0.0.1:{opcua_port}"
        client = await asyncio.to_thread(DoorClient, url, broker.port, opcua_url, token)
        flooder = await asyncio.to_thread(DoorClient, url, broker.port, opcua_url, token)
        samples: dict[tuple[str, str], list[float]] = {}
        written: dict[tuple[str, str], list[float]] = {}
        to_halt: dict[tuple[str, str], list[float]] = {}
        to_devices: dict[tuple[str, str], list[float]] = {}
        for _ in range(args.trials):
            for door in args.doors:
                for condition in CONDITIONS:
                    await to_idle(cell.worker)
                    await asyncio.to_thread(witness.tell, "arm")
                    if condition == OTHER:
                        await asyncio.to_thread(flooder.flood, door, floods[door])
                    flood = floods[door] if condition == SAME else 0
                    sent, wrote = await asyncio.to_thread(client.stop, door, flood)
                    if condition == OTHER:
                        await asyncio.to_thread(flooder.finish)
                    stamps = await asyncio.to_thread(witness.tell, "stamps")
                    if "None" in stamps:
                        raise RuntimeError(f"the {door} stop reached no device: {stamps}")
                    halted = max(float(stamps[1]), float(stamps[2]))
                    halt_began = cell.stops.last_halted_at
                    assert halt_began is not None
                    samples.setdefault((door, condition), []).append(halted - sent)
                    written.setdefault((door, condition), []).append(halted - wrote)
                    to_halt.setdefault((door, condition), []).append(halt_began - wrote)
                    to_devices.setdefault((door, condition), []).append(halted - halt_began)
        await to_idle(cell.worker)
        await asyncio.to_thread(client.close)
        await asyncio.to_thread(flooder.close)
        server.should_exit = True
        await serving
    await asyncio.to_thread(witness.close)
    rows = []
    for door in args.doors:
        for condition in CONDITIONS:
            after_written = percentiles_ms(written[(door, condition)])
            server = percentiles_ms(to_halt[(door, condition)])
            devices = percentiles_ms(to_devices[(door, condition)])
            rows.append(
                {
                    "door": door,
                    "condition": condition.format(flood=floods[door]),
                    **percentiles_ms(samples[(door, condition)]),
                    "target_p99_ms": 5.0,
                    "written_p50_ms": after_written["p50_ms"],
                    "written_p99_ms": after_written["p99_ms"],
                    "server_p50_ms": server["p50_ms"],
                    "server_p99_ms": server["p99_ms"],
                    "devices_p50_ms": devices["p50_ms"],
                    "devices_p99_ms": devices["p99_ms"],
                }
            )
    return rows


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--trials", type=int, default=30, help="stops per door and condition")
    parser.add_argument("--mqtt-flood", type=int, default=3000, help="MQTT commands ahead")
    parser.add_argument("--opcua-flood", type=int, default=300, help="OPC UA calls ahead")
    parser.add_argument("--http-flood", type=int, default=1000, help="HTTP requests ahead")
    parser.add_argument(
        "--doors", nargs="+", choices=DOORS, default=list(DOORS), help="the doors to measure"
    )
    parser.add_argument("--name", default="estop_doors", help="the result file's name")
    args = parser.parse_args(argv)
    logging.disable(logging.ERROR)  # every e-stop logs a fault; not what is measured
    with tempfile.TemporaryDirectory(prefix="bench-doors-") as data:
        rows = asyncio.run(run(args, Path(data)))
    floods = {"mqtt": args.mqtt_flood, "opcua": args.opcua_flood, "http": args.http_flood}
    emit(args.name, rows, {"trials": args.trials, "floods": floods})
    return rows


if __name__ == "__main__":
    main()
