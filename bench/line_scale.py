"""A line of N cells on one machine: the line view's lag, the broker's traffic per cell,
each cell's memory and CPU, and the e-stop of a few cells while all of them publish.

Who runs where, as `make line` runs a line (server/line/): Debian's mosquitto started
here on free ports (`start_broker`, the demo's configuration and ACL), N cells as
`python -m server` processes of their own (default 20) signed in as the demo's
`cell` user, and the line view (`python -m server.line.view`) opened in Debian's
Chromium (headless), which reads every cell from the broker's WebSocket listener
as a person's browser does.

The cells commission once: a template cell starts on a fresh data directory
(calibrations, CPU-bound), stops, and every cell starts on a copy of it. A line
whose cells all commission at once on two cores would measure the commissioning.

- `--busy` cells (default 3) run a production order of the demo part
  (POST /orders, a large quantity): a part after another, progress flowing.
- `--witnessed` cells (default 3, idle) each have their robot and glue simulators
  in a stop witness (bench/stop_witness.py, as `bench.plant_latency` uses it):
  every `--stop-every` seconds one of them is stopped in turn (POST /estop from
  the witness), then reset. The **device stop** is from the request leaving to
  the later of the robot receiving `stop` and the dispenser the valve-close write.
- the others are idle: their retained state, status and KPIs only.

Measured over `--seconds` (after every cell is IDLE and the view shows them all):
- **transition → subscriber**: a transition's own time (`since` in the cell's
  retained `state` message) to its arrival at an MQTT subscriber of `glue/+/+` in
  this process (the `line-view` user: what a line model in Python sees);
- **transition → line view screen**: the same time to the moment the line view's
  card of that cell shows the new state (a MutationObserver in the page, Date.now(),
  the same machine's clock);
- **traffic per cell**: the messages and bytes (topic and payload) the subscriber
  received from each cell, per second, for idle, busy and witnessed cells apart;
  one line view or dashboard subscribed receives exactly this;
- **memory**: each cell's unique memory (server and image process) at the end;
  **CPU**: each process's CPU seconds over the window, per second (1.0 = one core);
  the broker's and the browser's too.

Run: `python -m bench.line_scale` (`--cells 20 --busy 3 --witnessed 3 --seconds 120`).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import os
import shutil
import statistics
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import aiomqtt
import httpx
import psutil

from bench.estop_latency import StopWitness
from bench.plant_latency import Cell, auth, cell_environment, free_port, running, wait_idle
from bench.report import emit, percentiles_ms
from server.line.broker import DEMO_PASSWORDS, BrokerPorts, start_broker
from tests.processes import wait_answering

CHROMIUM = "/usr/bin/chromium"
LAUNCH_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run"]
SPEED_FACTOR = "3.0"  # the cells' simulated moves, as bench.plant_latency (and its witness)
# A frame's bound, not a figure (as bench.cell_memory): twenty cells' lowest-priority image
# processes starting at once on two cores wait long for their first frame.
CAMERA_TIMEOUT_S = "30"
CELL_SETTINGS = {
    "GLUE_APP_SIMULATION_SPEED_FACTOR": SPEED_FACTOR,
    "GLUE_APP_VISION_PROCESSING_TIMEOUT": CAMERA_TIMEOUT_S,
}
READY_S = 900.0  # twenty cells starting on two cores: a hang guard, not a figure
SETTLE_S = 120.0
# A request's bound, a hang guard: on two cores shared by twenty cells a reset's answer
# (after its probe of the devices) took more than 30 s.
CLIENT_TIMEOUT_S = 120.0
REFUSED_RESETS: list[str] = []  # why each reset of a witnessed cell was refused
ORDER_QUANTITY = 10_000  # more parts than any window makes

# Installed in the line view's page before its scripts run: every change of a card's
# shown state, with the page's clock (ms since the epoch). The page re-renders every
# card on each message, so only a changed text is a change.
OBSERVER = """
window.__shown = [];
const last = new Map();
new MutationObserver((records) => {
  const now = Date.now();
  for (const record of records) {
    const node = record.target.nodeType === 1 ? record.target : record.target.parentElement;
    if (!node || !node.classList || !node.classList.contains("state")) continue;
    const card = node.closest("section.cell");
    if (!card) continue;
    const text = node.textContent;
    if (last.get(card.dataset.cell) === text) continue;
    last.set(card.dataset.cell, text);
    window.__shown.push([now, card.dataset.cell, text]);
  }
}).observe(document, { subtree: true, childList: true, characterData: true });
"""


Seen = tuple[float, str, str, float]  # a state message: arrival, cell, state, its time
Made = tuple[str, str, float, float]  # a transition: cell, state, its time, first arrival


@dataclass
class Traffic:
    """What the subscriber received: per cell, messages and bytes; the state messages."""

    messages: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    octets: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    states: list[Seen] = field(default_factory=list)
    counting: bool = False


@contextlib.asynccontextmanager
async def subscriber(broker: BrokerPorts, traffic: Traffic) -> AsyncIterator[None]:
    """An MQTT subscriber of every cell's topics, as the line view subscribes."""
    ready = asyncio.Event()

    async def listen() -> None:
        password = DEMO_PASSWORDS["line-view"]
        async with aiomqtt.Client(
            broker.host, broker.mqtt, username="line-view", password=password
        ) as client:
            await client.subscribe("glue/+/+", qos=0)
            ready.set()
            async for message in client.messages:
                arrived = time.time()
                topic = message.topic.value
                payload = message.payload
                assert isinstance(payload, bytes)
                _, cell_id, kind = topic.split("/")
                if traffic.counting:
                    traffic.messages[cell_id] += 1
                    traffic.octets[cell_id] += len(topic) + len(payload)
                if kind == "state" and payload:
                    body = json.loads(payload)
                    if isinstance(body.get("since"), (int, float)):
                        traffic.states.append((arrived, cell_id, body["state"], body["since"]))

    task = asyncio.create_task(listen())
    await asyncio.wait_for(ready.wait(), 60)
    try:
        yield
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


def transitions(states: list[Seen], since: float) -> list[Made]:
    """(cell, state, its time, first arrival) of each transition made after `since`:
    a retained state is sent again (a reconnect, a run's details) with the same time."""
    seen: dict[tuple[str, float], Made] = {}
    for arrived, cell_id, state, at in states:
        if at >= since and (cell_id, at) not in seen:
            seen[(cell_id, at)] = (cell_id, state, at, arrived)
    return sorted(seen.values(), key=lambda found: found[2])


def screen_lags(made: list[Made], shown: list[tuple[float, str, str]]) -> tuple[list[float], int]:
    """For each transition, the first later change of that cell's card to that state:
    (the lags in seconds, how many transitions the screen never showed; a state left
    before the page drew it is one of them)."""
    by_cell: dict[str, list[tuple[float, str]]] = defaultdict(list)
    for at_ms, cell_id, text in shown:
        by_cell[cell_id].append((at_ms / 1000, text))
    lags, missed = [], 0
    used: dict[str, int] = defaultdict(int)
    for cell_id, state, at, _ in made:
        changes = by_cell[cell_id]
        index = used[cell_id]
        while index < len(changes) and changes[index][0] < at:
            index += 1
        found = next((i for i in range(index, len(changes)) if changes[i][1] == state), None)
        if found is None:
            missed += 1
            continue
        lags.append(changes[found][0] - at)
        used[cell_id] = found + 1
    return lags, missed


def unique_mb(pid: int) -> float:
    """Unique memory of a process and its descendants (a cell's server and image process)."""
    total = 0
    with contextlib.suppress(psutil.NoSuchProcess):
        parent = psutil.Process(pid)
        for process in (parent, *parent.children(recursive=True)):
            with contextlib.suppress(psutil.NoSuchProcess):
                total += process.memory_full_info().uss
    return total / 2**20


def cpu_seconds(pid: int) -> float:
    """CPU seconds (user + system) of a process and its descendants so far."""
    total = 0.0
    with contextlib.suppress(psutil.NoSuchProcess):
        parent = psutil.Process(pid)
        for process in (parent, *parent.children(recursive=True)):
            with contextlib.suppress(psutil.NoSuchProcess):
                times = process.cpu_times()
                total += times.user + times.system
    return total


@contextlib.contextmanager
def line_view(broker: BrokerPorts, logs: Path) -> Iterator[str]:
    """`python -m server.line.view` (what `make line` starts), its URL."""
    port = free_port()
    log = (logs / "line-view.log").open("wb")
    argv = [sys.executable, "-m", "server.line.view", "--port", str(port)]
    process = psutil.Popen(
        [*argv, "--broker-ws", broker.websocket_url],
        stdout=log,
        stderr=log,
        env=cell_environment({}),
    )
    log.close()
    url = f"http://127.0.0.1:{port}/"
    try:
        wait_answering(process, url, 60, log=logs / "line-view.log")
        yield url
    finally:
        process.terminate()
        process.wait(10)


def commission_template(data: Path) -> Path:
    """A data directory commissioned once (a cell started on it until IDLE, then stopped)."""
    template = Cell(
        "template",
        free_port(),
        data / "template",
        cell_environment(CELL_SETTINGS),
    )

    async def idle() -> None:
        async with httpx.AsyncClient(timeout=CLIENT_TIMEOUT_S) as client:
            await wait_ready(client, template)
        if not any((template.data / "workpieces").glob("*.json")):
            raise RuntimeError("the template cell did not commission itself (data/template.log)")

    with running([template], data):
        asyncio.run(idle())
    return template.data


def make_cells(
    count: int, witnessed: int, broker: BrokerPorts, template: Path, data: Path
) -> list[Cell]:
    """`count` cells on copies of `template`; the first `witnessed` with a stop witness."""
    cells = []
    for n in range(1, count + 1):
        name = f"cell-{n:02d}"
        extra = {
            "GLUE_APP_CELL_ID": name,
            **CELL_SETTINGS,
            "GLUE_APP_MQTT_URL": broker.mqtt_url,
            "GLUE_APP_MQTT_USERNAME": "cell",
            "GLUE_APP_MQTT_PASSWORD": DEMO_PASSWORDS["cell"],
        }
        witness = StopWitness() if n <= witnessed else None
        if witness is not None:
            extra["GLUE_APP_ROBOT_IP"] = "127.0.0.1"
            extra["GLUE_APP_ROBOT_PORT"] = str(witness.robot_port)
            extra["GLUE_APP_GLUE_CONTROLLER_PORT"] = f"tcp://127.0.0.1:{witness.glue_port}"
        shutil.copytree(template, data / name)
        cells.append(Cell(name, free_port(), data / name, cell_environment(extra), witness=witness))
    return cells


async def wait_ready(client: httpx.AsyncClient, cell: Cell) -> None:
    """Until the cell is IDLE; RuntimeError with its stop reason if it went to ERROR."""
    deadline = time.monotonic() + READY_S
    while True:
        assert cell.process is not None and cell.process.poll() is None, f"{cell.name} exited"
        with contextlib.suppress(httpx.HTTPError):
            answer = await client.get(f"{cell.url}/state", headers=auth(cell))
            if answer.status_code == 200:
                state = answer.json()
                if state["state"] == "IDLE":
                    return
                if state["state"] == "ERROR":
                    raise RuntimeError(f"{cell.name} is in ERROR: {state.get('stop_reason')}")
        if time.monotonic() > deadline:
            raise TimeoutError(f"{cell.name} did not reach IDLE")
        await asyncio.sleep(0.2)


async def stop_and_reset(client: httpx.AsyncClient, cell: Cell) -> float:
    """One stop through the cell's witness, then a reset: the device stop in seconds."""
    assert cell.witness is not None
    words = await asyncio.to_thread(cell.witness.tell, "fire")
    assert words[0] == "stopped", f"{cell.name}: the e-stop failed: {' '.join(words)}"
    assert words[2] == "True", f"{cell.name}: the valve does not read closed after the stop"
    deadline = time.monotonic() + SETTLE_S
    # A reset probes the devices; a starved image process misses the probe's bound and the
    # reset is refused (409): pressed again, as a person would, and counted.
    while (answer := await client.post(f"{cell.url}/reset", headers=auth(cell))).status_code == 409:
        REFUSED_RESETS.append(answer.json().get("message", ""))
        assert time.monotonic() < deadline, f"{cell.name}: reset refused: {answer.text}"
        await asyncio.sleep(1.0)
    assert answer.status_code == 202, answer.text
    await wait_idle(client, cell, SETTLE_S)
    return float(words[1])


async def start_order(client: httpx.AsyncClient, cell: Cell) -> None:
    body = {"workpiece_id": "demo", "quantity": ORDER_QUANTITY}
    answer = await client.post(f"{cell.url}/orders", json=body, headers=auth(cell))
    assert answer.status_code == 201, f"{cell.name}: {answer.status_code} {answer.text}"


async def parts_made(client: httpx.AsyncClient, cell: Cell) -> int:
    """Parts the cell's orders have made so far."""
    answer = await client.get(f"{cell.url}/orders", headers=auth(cell))
    answer.raise_for_status()
    body = answer.json()
    orders = body if isinstance(body, list) else body.get("orders", [])
    return sum(int(order.get("parts_made", 0) or 0) for order in orders)


def rate_row(what: str, cells: list[Cell], traffic: Traffic, seconds: float) -> dict[str, Any]:
    messages = [traffic.messages.get(cell.name, 0) / seconds for cell in cells]
    octets = [traffic.octets.get(cell.name, 0) / seconds for cell in cells]
    return {
        "figure": f"traffic per cell, {what} ({len(cells)})",
        "messages_per_s": round(statistics.mean(messages), 3) if messages else 0.0,
        "bytes_per_s": round(statistics.mean(octets), 1) if octets else 0.0,
        "max_bytes_per_s": round(max(octets), 1) if octets else 0.0,
    }


async def run(
    args: argparse.Namespace, data: Path, template: Path
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    from playwright.async_api import async_playwright

    broker = BrokerPorts("127.0.0.1", free_port(), free_port())
    broker_process = start_broker(broker, data / "broker")
    cells: list[Cell] = []
    traffic = Traffic()
    stops: list[float] = []
    notes: dict[str, Any] = {}
    try:
        cells = make_cells(args.cells, args.witnessed, broker, template, data)
        witnessed = cells[: args.witnessed]
        busy = cells[args.witnessed : args.witnessed + args.busy]
        idle = cells[args.witnessed + args.busy :]
        started_up = time.monotonic()
        with running(cells, data), line_view(broker, data) as view_url:
            async with (
                httpx.AsyncClient(timeout=CLIENT_TIMEOUT_S) as client,
                subscriber(broker, traffic),
            ):
                for cell in cells:
                    await wait_ready(client, cell)
                notes["all_idle_after_s"] = round(time.monotonic() - started_up, 1)
                for cell in witnessed:
                    said = await asyncio.to_thread(
                        cell.witness.tell,  # type: ignore[union-attr]
                        f"server {cell.url} {auth(cell)['Authorization'].split()[1]}",
                    )
                    assert said == ["ready"], said
                async with async_playwright() as playwright:
                    browser = await playwright.chromium.launch(
                        executable_path=CHROMIUM, args=LAUNCH_ARGS
                    )
                    try:
                        page = await browser.new_page(bypass_csp=True)  # for the observer
                        await page.add_init_script(OBSERVER)
                        await page.goto(view_url)
                        await every_card_shown(page, len(cells))
                        browser_pid = browser_process_pid()
                        for cell in busy:
                            await start_order(client, cell)
                        pids = {cell.name: cell.process.pid for cell in cells if cell.process}
                        cpu_before = {name: cpu_seconds(pid) for name, pid in pids.items()}
                        broker_cpu = cpu_seconds(broker_process.pid)
                        browser_cpu = cpu_seconds(browser_pid) if browser_pid else 0.0
                        began, window_start = time.time(), time.monotonic()
                        traffic.counting = True
                        turn = 0
                        while time.monotonic() - window_start < args.seconds:
                            if witnessed:
                                cell = witnessed[turn % len(witnessed)]
                                stops.append(await stop_and_reset(client, cell))
                                turn += 1
                            await asyncio.sleep(args.stop_every)
                        traffic.counting = False
                        window = time.monotonic() - window_start
                        cpu = {
                            n: (cpu_seconds(p) - cpu_before[n]) / window for n, p in pids.items()
                        }
                        notes["broker_cpu"] = round(
                            (cpu_seconds(broker_process.pid) - broker_cpu) / window, 4
                        )
                        if browser_pid:
                            notes["browser_cpu"] = round(
                                (cpu_seconds(browser_pid) - browser_cpu) / window, 4
                            )
                        notes["parts_made_by_busy_cells"] = [
                            await parts_made(client, cell) for cell in busy
                        ]
                        await asyncio.sleep(2.0)  # the last transitions reach the screen
                        shown = await page.evaluate("window.__shown")
                    finally:
                        await browser.close()
                memory = {cell.name: unique_mb(pids[cell.name]) for cell in cells}
                notes["broker_rss_mb"] = round(
                    psutil.Process(broker_process.pid).memory_info().rss / 2**20, 1
                )
    finally:
        broker_process.terminate()
        broker_process.wait(timeout=30)
        for cell in cells:
            if cell.witness is not None:
                await asyncio.to_thread(cell.witness.close)
    made = [t for t in transitions(traffic.states, began) if t[2] <= began + window]
    to_screen, missed = screen_lags(made, [(float(at), str(c), str(t)) for at, c, t in shown])
    notes["resets_refused"] = len(REFUSED_RESETS)
    notes["reset_refusals"] = sorted(set(REFUSED_RESETS))[:3]
    notes["transitions"] = len(made)
    notes["transitions_not_seen_on_screen"] = missed
    notes["window_s"] = round(window, 1)
    groups = (("witnessed", witnessed), ("busy", busy), ("idle", idle))
    rows: list[dict[str, Any]] = [
        {
            "figure": f"transition → MQTT subscriber ({len(cells)} cells)",
            **percentiles_ms([arrived - at for _, _, at, arrived in made]),
        },
        {
            "figure": f"transition → line view screen ({len(cells)} cells)",
            **percentiles_ms(to_screen),
        },
        {
            "figure": f"device stop, witnessed cells, while {len(cells)} cells publish",
            **percentiles_ms(stops),
        },
        *(rate_row(what, group, traffic, window) for what, group in groups if group),
    ]
    for what, group in groups:
        if group:
            rows.append(
                {
                    "figure": f"per cell, {what} ({len(group)})",
                    "unique_mb": round(statistics.mean(memory[c.name] for c in group), 1),
                    "max_unique_mb": round(max(memory[c.name] for c in group), 1),
                    "cpu_cores": round(statistics.mean(cpu[c.name] for c in group), 4),
                }
            )
    notes["cells_unique_mb_total"] = round(sum(memory.values()), 1)
    return rows, notes


async def every_card_shown(page: Any, count: int) -> None:
    """Until the line view shows `count` cells (asked from here: the page's policy refuses
    a script given as text, as Playwright's wait_for_function sends it)."""
    deadline = time.monotonic() + READY_S
    while await page.locator("section.cell").count() < count:
        assert time.monotonic() < deadline, "the line view does not show every cell"
        await asyncio.sleep(0.2)


def browser_process_pid() -> int | None:
    """The headless Chromium this process started (its CPU is the line view's cost)."""
    for child in psutil.Process().children(recursive=True):
        with contextlib.suppress(psutil.NoSuchProcess):
            if "chrom" in child.name() and child.parent() and "chrom" not in child.parent().name():
                return child.pid
    return None


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--cells", type=int, default=20)
    parser.add_argument("--busy", type=int, default=3, help="cells running an order")
    parser.add_argument("--witnessed", type=int, default=3, help="cells whose stop is timed")
    parser.add_argument("--seconds", type=float, default=120.0, help="the measured window")
    parser.add_argument(
        "--stop-every", type=float, default=3.0, help="seconds between a reset and the next stop"
    )
    args = parser.parse_args(argv)
    assert args.busy + args.witnessed <= args.cells, "more busy and witnessed cells than cells"
    logging.disable(logging.ERROR)
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="bench-line-") as data:
        template = commission_template(Path(data))
        rows, notes = asyncio.run(run(args, Path(data), template))
    emit(
        "line_scale",
        rows,
        {
            "cells": args.cells,
            "busy": args.busy,
            "witnessed": args.witnessed,
            "load_average_before": load_before,
            "load_average_after": os.getloadavg(),
            **notes,
        },
    )
    return rows


if __name__ == "__main__":
    main()
