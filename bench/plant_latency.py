"""The plant's view of a transition: how long until an MQTT subscriber and an OPC UA
subscription see it, and whether serving both makes the software stop any slower.

Who runs where, as a line runs: Debian's mosquitto, and four cells as server
processes of their own (`python -m server`, simulated devices): `cell-1` with
OPC UA and MQTT on, `cell-2` and `cell-3` with MQTT on (three cells on one
broker), and `plain` with both off; and `control`, a second cell with both off,
measured exactly as `plain` is. Two identical cells differ too (where each
process lands on the two cores, what else runs at that moment): the gap between
`control` and `plain` in the same run is the noise floor that the gap between
`cell-1` and `plain` is read against. This process is the plant: an MQTT
subscriber to every cell's `event` topic, a Sparkplug B host subscribed to
cell-1's DDATA (cell-1 is also an edge node, group `bench`) and an OPC UA client
subscribed to cell-1's `CellState`, in a process of their own, and the HTTP client that drives
the cycles, in this one.

The stops of `cell-1`, `plain` and `control` are sent by a witness each
(bench/stop_witness.py, a process of its own holding that cell's robot and glue
simulators and a kept-alive HTTP client, as an HMI holds one), so a stop is timed
twice: the **device stop**, from the request leaving to the later of the robot
receiving `stop` and the dispenser receiving the valve-close write (the
simulators' own stamps, as `bench.estop_latency` takes them), and the
**answer**, the POST /estop round trip.
`cell-2` and `cell-3` run their simulators inside, as `python -m server` does;
their stops are sent from here.

A cycle has two stops per cell, one in each condition:
- `after a reset` (the condition of the first runs): each cell is stopped in IDLE,
  each right after the previous cell's stop was answered, the cells having been
  reset (and the last of them settled) just before;
- `spraying`: every cell starts the demo run, and once all of them are on the spray
  path (waypoint 2 or later, the valve open, progress flowing to the plant) each
  is stopped in turn. This is when a stop is pressed on a line.
The order of the stops alternates from cycle to cycle, so neither the cell with
the interfaces nor the one without always goes first. Each transition carries
the time the cell made it (`timestamp` on MQTT, `since` in CellState, the
`State/Since` metric in Sparkplug's DDATA); a lag is the time the plant received
it minus that time, on the same machine's clock.

- `mqtt`: transition → MQTT subscriber, over the three cells' transitions.
- `sparkplug`: transition → Sparkplug B DDATA (cell-1's, to the `scada` user).
- `opcua`: transition → OPC UA data change of cell-1's CellState, with the
  subscription's publishing interval (`--publishing-ms`, the server's floor is
  what asyncua grants) included: a client sees a change at the next publish.
- `written`: transition → the server's write of that CellState (the value's
  ServerTimestamp): the OPC UA data change's lag before the publishing interval.
- `alarms`: the cell raising or clearing an alarm (an e-stop's fault recorded, the
  reset that clears it) → the OPC UA event on a subscription to cell-1's Server
  object, the event's own `Time` against its arrival, the same publishing interval
  included.
- device stop and answer, on cell-1 (every interface on and subscribed to),
  on `plain` (both off) and on `control` (both off), per condition, in the same run.

Run: `python -m bench.plant_latency` (`--cycles 100` by default; about six
minutes on two cores, after the four cells have commissioned).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import multiprocessing
import os
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import aiomqtt
import httpx

from bench.estop_latency import StopWitness
from bench.report import emit, percentiles_ms
from server.line.broker import DEMO_PASSWORDS, BrokerPorts, start_broker

ROOT = Path(__file__).resolve().parents[1]
READY_S = 600.0  # four cells commissioning at once on a shared machine: a hang guard
SETTLE_S = 60.0
CONDITIONS = ("after a reset", "spraying")
SPRAY_DEMO = {"contour_matching": False, "workpiece_id": "demo"}
SPEED_FACTOR = "3.0"  # the witness's simulators' speed (bench/stop_witness.py), for every cell
WITHOUT_INTERFACES = ("plain", "control")
SPARKPLUG_GROUP = "bench"  # cell-1's Sparkplug B group
WITNESSED = ("cell-1", *WITHOUT_INTERFACES)  # each stop timed at the devices too
WRITTEN = "_written"  # the key this bench adds to a CellState: when the server wrote it


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@dataclass
class Cell:
    """One server process of the line, and what the benchmark needs to drive it."""

    name: str
    port: int
    data: Path
    env: dict[str, str]
    opcua_port: int | None = None
    process: subprocess.Popen[bytes] | None = None
    token: str = ""
    witness: StopWitness | None = None  # sends this cell's stops and times them
    device_stops: dict[str, list[float]] = field(default_factory=dict)
    answers: dict[str, list[float]] = field(default_factory=dict)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"


def cell_environment(extra: dict[str, str]) -> dict[str, str]:
    """This checkout's server, no cell settings from the shell, then `extra`."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("GLUE_APP_")}
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return {**env, **extra}


@contextlib.contextmanager
def running(cells: list[Cell], logs: Path) -> Iterator[None]:
    try:
        for cell in cells:
            log = (logs / f"{cell.name}.log").open("wb")
            argv = [sys.executable, "-m", "server", "--port", str(cell.port)]
            argv += ["--data-dir", str(cell.data)]
            cell.process = subprocess.Popen(
                argv, stdout=log, stderr=subprocess.STDOUT, env=cell.env
            )
            log.close()
        yield
    finally:
        for cell in cells:
            if cell.process is not None and cell.process.poll() is None:
                cell.process.terminate()
        for cell in cells:
            if cell.process is not None:
                try:
                    cell.process.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    cell.process.kill()


async def wait_idle(client: httpx.AsyncClient, cell: Cell, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while True:
        assert cell.process is not None and cell.process.poll() is None, f"{cell.name} exited"
        with contextlib.suppress(httpx.HTTPError):
            answer = await client.get(f"{cell.url}/state", headers=auth(cell))
            if answer.status_code == 200 and answer.json()["state"] == "IDLE":
                return
        if time.monotonic() > deadline:
            raise TimeoutError(f"{cell.name} did not reach IDLE")
        await asyncio.sleep(0.05)


def auth(cell: Cell) -> dict[str, str]:
    if not cell.token:
        token_file = cell.data / "admin.token"
        if token_file.exists():
            cell.token = token_file.read_text().strip()
    return {"Authorization": f"Bearer {cell.token}"}


@contextlib.asynccontextmanager
async def mqtt_events(
    broker: BrokerPorts, received: list[tuple[float, dict[str, Any]]]
) -> AsyncIterator[None]:
    """Every cell's `event` messages, each with the time it arrived here."""
    ready = asyncio.Event()

    async def listen() -> None:
        login = {"username": "line-view", "password": DEMO_PASSWORDS["line-view"]}
        async with aiomqtt.Client(broker.host, broker.mqtt, **login) as client:
            await client.subscribe("glue/+/event", qos=1)
            ready.set()
            async for message in client.messages:
                arrived = time.time()
                received.append((arrived, json.loads(bytes(message.payload))))

    task = asyncio.create_task(listen())
    await asyncio.wait_for(ready.wait(), 30)
    try:
        yield
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


@contextlib.asynccontextmanager
async def opcua_changes(
    port: int, publishing_ms: float, received: list[tuple[float, dict[str, Any]]]
) -> AsyncIterator[float]:
    """cell-1's CellState changes, each with the time it arrived; yields the granted
    publishing interval (ms)."""
    from asyncua import Client

    class Handler:
        def datachange_notification(self, node: Any, value: Any, data: Any) -> None:
            arrived = time.time()
            with contextlib.suppress(ValueError, TypeError):
                document = json.loads(value)
                written = data.monitored_item.Value.ServerTimestamp
                document[WRITTEN] = written.timestamp() if written is not None else None
                received.append((arrived, document))

    client = Client(f"opc.tcp://127.0.0.1:{port}")
    await client.connect()
    try:
        namespace = await client.get_namespace_index("urn:glue-cell:packml")
        node = client.get_node(f"ns={namespace};s=cell-1.CellState")
        subscription = await client.create_subscription(publishing_ms, Handler())
        await subscription.subscribe_data_change(node)
        granted = float(subscription.parameters.RequestedPublishingInterval)
        yield granted
        await subscription.delete()
    finally:
        await client.disconnect()


@contextlib.asynccontextmanager
async def opcua_alarms(
    port: int, publishing_ms: float, received: list[tuple[float, float]]
) -> AsyncIterator[None]:
    """cell-1's alarm events on its Server object: (arrival, the event's Time) of each."""
    from asyncua import Client, ua

    class Handler:
        def event_notification(self, event: Any) -> None:
            arrived = time.time()
            if event.Time is not None:
                received.append((arrived, event.Time.timestamp()))

    client = Client(f"opc.tcp://127.0.0.1:{port}")
    await client.connect()
    try:
        subscription = await client.create_subscription(publishing_ms, Handler())
        kinds = [ua.ObjectIds.TripAlarmType, ua.ObjectIds.OffNormalAlarmType]
        await subscription.subscribe_events(client.nodes.server, kinds, queuesize=1000)
        yield
        await subscription.delete()
    finally:
        await client.disconnect()


Received = list[tuple[float, dict[str, Any]]]
Alarms = list[tuple[float, float]]


@contextlib.asynccontextmanager
async def sparkplug_ddata(broker: BrokerPorts, received: Received) -> AsyncIterator[None]:
    """cell-1's Sparkplug DDATA that carry a transition (`State/Since`), each with the
    time it arrived, as `{"cell_id", "since"}` (seconds)."""
    from server.mqtt.sparkplug.payload import decode

    ready = asyncio.Event()

    async def listen() -> None:
        login = {"username": "scada", "password": DEMO_PASSWORDS["scada"]}
        async with aiomqtt.Client(broker.host, broker.mqtt, **login) as client:
            await client.subscribe(f"spBv1.0/{SPARKPLUG_GROUP}/DDATA/cell-1/cell", qos=0)
            ready.set()
            async for message in client.messages:
                arrived = time.time()
                metrics = {m.name: m.value for m in decode(bytes(message.payload)).metrics}
                since = metrics.get("State/Since")
                if isinstance(since, int):
                    received.append((arrived, {"cell_id": "cell-1", "since": since / 1000}))

    task = asyncio.create_task(listen())
    await asyncio.wait_for(ready.wait(), 30)
    try:
        yield
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


async def listen(
    broker: BrokerPorts, opcua_port: int, publishing_ms: float, stop: Any, ready: Any
) -> tuple[Received, Received, Alarms, Received, float]:
    mqtt: Received = []
    opcua: Received = []
    alarms: Alarms = []
    sparkplug: Received = []
    async with (
        mqtt_events(broker, mqtt),
        sparkplug_ddata(broker, sparkplug),
        opcua_changes(opcua_port, publishing_ms, opcua) as granted,
        opcua_alarms(opcua_port, publishing_ms, alarms),
    ):
        ready.set()
        while not stop.is_set():
            await asyncio.sleep(0.05)
    return mqtt, opcua, alarms, sparkplug, granted


def plant(
    broker: BrokerPorts, opcua_port: int, publishing_ms: float, stop: Any, ready: Any, out: Any
) -> None:
    """The plant's subscribers, in a process of their own: what they receive must not
    share a loop (or the interpreter lock) with the HTTP client timing the stops."""
    logging.disable(logging.ERROR)
    out.send(asyncio.run(listen(broker, opcua_port, publishing_ms, stop, ready)))


async def stop(client: httpx.AsyncClient, cell: Cell, condition: str) -> None:
    """POST /estop; through the cell's witness (both figures kept) if it has one."""
    if cell.witness is None:
        answer = await client.post(
            f"{cell.url}/estop", json={"reason": "plant latency benchmark"}, headers=auth(cell)
        )
        assert answer.status_code == 202, answer.text
        return
    words = await asyncio.to_thread(cell.witness.tell, "fire")
    assert words[0] == "stopped", f"{cell.name}: the e-stop failed: {' '.join(words)}"
    assert words[2] == "True", f"{cell.name}: the valve does not read closed after the stop"
    cell.device_stops.setdefault(condition, []).append(float(words[1]))
    cell.answers.setdefault(condition, []).append(float(words[4]))


async def reset_all(client: httpx.AsyncClient, cells: list[Cell]) -> None:
    for cell in cells:
        answer = await client.post(f"{cell.url}/reset", headers=auth(cell))
        assert answer.status_code == 202, answer.text
        await wait_idle(client, cell, SETTLE_S)


async def wait_spraying(client: httpx.AsyncClient, cell: Cell) -> None:
    """Until the cell's run is on its spray path (waypoint 2 or later)."""
    deadline = time.monotonic() + SETTLE_S
    while True:
        state = (await client.get(f"{cell.url}/state", headers=auth(cell))).json()
        assert state["state"] == "EXECUTING_TRAJECTORY", f"{cell.name}: {state['state']}"
        progress = (state.get("operation") or {}).get("progress") or {}
        if progress.get("waypoint", 0) >= 2:
            return
        if time.monotonic() > deadline:
            raise TimeoutError(f"{cell.name} did not reach its spray path")
        await asyncio.sleep(0.02)


async def alone(client: httpx.AsyncClient, cell: Cell, count: int) -> None:
    """`count` times, `cell` alone while the others stay idle: a stop after a reset,
    then a run started and stopped on its spray path, then a reset. Its stops are
    not kept: the stop figures compare cells under the same load, in `cycles`."""
    for _ in range(count):
        await stop(client, cell, "alone")
        await reset_all(client, [cell])
        answer = await client.post(f"{cell.url}/start", json=SPRAY_DEMO, headers=auth(cell))
        assert answer.status_code == 202, answer.text
        await wait_spraying(client, cell)
        await stop(client, cell, "alone")
        await reset_all(client, [cell])


async def cycles(client: httpx.AsyncClient, cells: list[Cell], count: int) -> None:
    """`count` times: a stop of every cell after a reset, then one while every cell
    sprays; each stop is answered before the next is sent, the order alternating."""
    for n in range(count):
        order = cells if n % 2 == 0 else cells[::-1]
        for cell in order:
            await stop(client, cell, "after a reset")
        await reset_all(client, cells)
        for cell in cells:
            answer = await client.post(f"{cell.url}/start", json=SPRAY_DEMO, headers=auth(cell))
            assert answer.status_code == 202, answer.text
        for cell in cells:
            await wait_spraying(client, cell)
        for cell in order:
            await stop(client, cell, "spraying")
        await reset_all(client, cells)


def written_lags(received: Received, since: float, until: float) -> list[float]:
    """The server's write of CellState (its ServerTimestamp) minus the transition's own
    time, once per transition: the OPC UA lag before the publishing interval's wait."""
    as_written = [(document[WRITTEN], document) for _, document in received if document[WRITTEN]]
    return lags(as_written, "since", since, until)


def lags(
    received: list[tuple[float, dict[str, Any]]], stamp: str, since: float, until: float
) -> list[float]:
    """Arrival minus the transition's own time, once per transition made in [since, until).

    CellState also changes within a state (a device's health, a waypoint), and a
    subscription starts with the current value: only the first sight of a
    transition of the cycles counts.
    """
    seen: set[tuple[Any, float]] = set()
    found = []
    for arrived, document in received:
        at = document.get(stamp)
        key = (document.get("cell_id"), float(at)) if at is not None else None
        if key is None or not since <= key[1] < until or key in seen:
            continue
        seen.add(key)
        found.append(arrived - key[1])
    return found


async def run(cycles_count: int, publishing_ms: float, data: Path) -> list[dict[str, Any]]:
    broker = BrokerPorts("127.0.0.1", free_port(), free_port())
    mqtt_url = broker.mqtt_url
    names = ("cell-1", "cell-2", "cell-3", "plain", "control")
    cells: list[Cell] = []
    for name in names:
        extra = {"GLUE_APP_CELL_ID": name, "GLUE_APP_SIMULATION_SPEED_FACTOR": SPEED_FACTOR}
        if name not in WITHOUT_INTERFACES:
            extra["GLUE_APP_MQTT_URL"] = mqtt_url  # the line broker's demo `cell` user
            extra["GLUE_APP_MQTT_USERNAME"] = "cell"
            extra["GLUE_APP_MQTT_PASSWORD"] = DEMO_PASSWORDS["cell"]
        witness = await asyncio.to_thread(StopWitness) if name in WITNESSED else None
        if witness is not None:
            extra["GLUE_APP_ROBOT_IP"] = "127.0.0.1"
            extra["GLUE_APP_ROBOT_PORT"] = str(witness.robot_port)
            extra["GLUE_APP_GLUE_CONTROLLER_PORT"] = f"tcp://127.0.0.1:{witness.glue_port}"
        cell = Cell(name, free_port(), data / name, cell_environment(extra), witness=witness)
        if name == "cell-1":
            cell.opcua_port = free_port()
            cell.env["GLUE_APP_OPCUA_ENDPOINT"] = f"opc.tcp://127.0.0.1:{cell.opcua_port}"
            cell.env["GLUE_APP_SPARKPLUG_GROUP"] = SPARKPLUG_GROUP
        cells.append(cell)
    broker_process = start_broker(broker, data / "broker")
    try:
        with running(cells, data):
            async with httpx.AsyncClient(timeout=30) as client:
                for cell in cells:
                    await wait_idle(client, cell, READY_S)
                    if cell.witness is not None:
                        auth(cell)
                        said = await asyncio.to_thread(
                            cell.witness.tell, f"server {cell.url} {cell.token}"
                        )
                        assert said == ["ready"], said
                assert cells[0].opcua_port is not None
                context = multiprocessing.get_context("spawn")
                stop, ready = context.Event(), context.Event()
                receiving, out = context.Pipe(duplex=False)
                listener = context.Process(
                    target=plant,
                    args=(broker, cells[0].opcua_port, publishing_ms, stop, ready, out),
                )
                listener.start()
                try:
                    assert await asyncio.to_thread(ready.wait, 60), "the plant did not subscribe"
                    started = time.time()
                    await cycles(client, cells, cycles_count)
                    await asyncio.sleep(2.0)  # the last transitions reach the plant
                    line_ended = time.time()
                    await alone(client, cells[0], cycles_count)
                    await asyncio.sleep(2.0)
                    alone_ended = time.time()
                    stop.set()
                    mqtt, opcua, alarms, sparkplug, granted = await asyncio.to_thread(
                        receiving.recv
                    )
                finally:
                    stop.set()
                    listener.join(30)
                    if listener.is_alive():
                        listener.kill()
    finally:
        broker_process.terminate()
        broker_process.wait(timeout=30)
        for cell in cells:
            if cell.witness is not None:
                await asyncio.to_thread(cell.witness.close)
    compared = (
        (cells[0], "OPC UA + MQTT + Sparkplug on"),
        (cells[3], "both off"),
        (cells[4], "both off, control cell"),
    )
    stops = []
    for condition in CONDITIONS:
        for what, of in (("device stop", "device_stops"), ("answer", "answers")):
            for cell, label in compared:
                samples = getattr(cell, of).get(condition, [])
                stops.append({"figure": f"{what}, {condition}, {label}", **percentiles_ms(samples)})
    phases = (
        ("every cell at once", started, line_ended),
        ("cell-1 alone", line_ended, alone_ended),
    )
    seen = []
    for phase, since, until in phases:
        alarm_lags = [arrived - at for arrived, at in alarms if since <= at < until]
        seen += [
            {
                "figure": f"transition → MQTT subscriber, {phase}",
                **percentiles_ms(lags(mqtt, "timestamp", since, until)),
            },
            {
                "figure": f"transition → Sparkplug B DDATA, {phase}",
                **percentiles_ms(lags(sparkplug, "since", since, until)),
            },
            {
                "figure": f"transition → OPC UA data change ({granted:g} ms), {phase}",
                **percentiles_ms(lags(opcua, "since", since, until)),
            },
            {
                "figure": f"alarm → OPC UA event ({granted:g} ms), {phase}",
                **percentiles_ms(alarm_lags),
            },
            {
                "figure": f"transition → CellState written (its ServerTimestamp), {phase}",
                **percentiles_ms(written_lags(opcua, since, until)),
            },
        ]
    return [
        *seen,
        *stops,
    ]


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--cycles", type=int, default=100, help="e-stop and reset cycles")
    parser.add_argument(
        "--publishing-ms", type=float, default=10.0, help="OPC UA publishing interval asked for"
    )
    args = parser.parse_args(argv)
    logging.disable(logging.ERROR)
    with tempfile.TemporaryDirectory(prefix="bench-plant-") as data:
        rows = asyncio.run(run(args.cycles, args.publishing_ms, Path(data)))
    emit("plant_latency", rows, {"cycles": args.cycles, "cells": 5})
    return rows


if __name__ == "__main__":
    main()
