"""Resident memory of a running server: at start, after 1M events, after 10k operations.

Every buffer in the server is meant to be bounded (the transition history, the
processing-time window, each WebSocket client's mailbox, the journal's
backlog, the metrics), so memory must level off however long the cell runs.

The server is the production app with its full persistence (journal in
SQLite, state snapshot file, KPIs, metrics) served by uvicorn in this process,
with one WebSocket-like bus subscriber draining every message; the devices are
no-op and each operation completes at once, so a million events take minutes
rather than days. Events go straight to the worker in batches (each awaited
until durable), not over HTTP: the HTTP layer holds nothing between requests.

- start: after start-up and a warm-up of 10k events (first-use allocations,
  caches, SQLite's page cache), with a full garbage collection;
- after --events (default 1M) events of the cell's cycle (start, pause,
  resume, cancel, calibrate, cancel, estop, reset);
- after --operations (default 10k) operations run to completion
  (start → OPERATION_COMPLETED → IDLE).
Target: growth under 10 MB.

`--cell` measures instead the whole cell as `python -m server` runs it, each
process apart (server, image process, resource tracker), after start-up and
after `--runs` spray runs, with the simulators in the server's process and
again apart from it (bench/cell_memory.py); with `--soak-minutes`, runs go on
that long and the cell is measured every `--every-minutes`. Targets: the cell's unique memory
after the runs at most 250 MB simulated, 150 MB with the devices elsewhere.
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import logging
import tempfile
import time
from pathlib import Path
from typing import Any

import psutil

from bench import cell_memory
from bench.engine_throughput import DEMO_PART, START_DEMO, NullDevice, event_sequence, submit_all
from bench.report import emit
from server.bootstrap.cell import Cell
from server.bootstrap.latency import tune_garbage_collection
from server.core.infra.bus import SubscriptionClosed
from server.core.machine.transitions import Event, State
from server.core.worker.devices import CellDevices
from server.core.worker.worker import Worker
from server.settings.model import Settings
from tests.serving import serve

BATCH = 500  # events in flight at once: below event_queue_size and the journal backlog limit


async def done_at_once(ctx: Any) -> dict[str, Any]:
    return {"done": True}


def rss_mb() -> float:
    gc.collect()
    return psutil.Process().memory_info().rss / 2**20


async def drive(worker: Worker, events: list[Event]) -> None:
    for first in range(0, len(events), BATCH):
        await submit_all(worker, events[first : first + BATCH])


async def run_operations(worker: Worker, count: int) -> None:
    for _ in range(count):
        outcome = await worker.request(Event.START_REQUESTED, source="bench", payload=START_DEMO)
        assert outcome.accepted, outcome.message
        while worker.ctx.state is not State.IDLE:
            await asyncio.sleep(0)


async def measure(event_count: int, operation_count: int) -> list[dict[str, Any]]:
    devices = CellDevices(NullDevice("robot"), NullDevice("glue"), NullDevice("camera"))  # type: ignore[arg-type]
    operations = dict.fromkeys(
        ("trajectory", "calibrate_robot", "calibrate_camera", "create_workpiece"), done_at_once
    )
    with tempfile.TemporaryDirectory() as directory:
        settings = Settings(data_path=Path(directory), commission_simulated_cell=False)
        cell = Cell(settings, devices=devices, operations=operations)
        tune_garbage_collection()  # as python -m server does
        async with serve(cell):
            worker = cell.worker
            assert worker is not None and cell.stores is not None
            cell.stores.workpieces.put("demo", DEMO_PART)
            while worker.ctx.state is not State.IDLE:
                await asyncio.sleep(0.01)
            subscription = cell.bus.subscribe(maxsize=BATCH * 4)

            async def drain() -> None:
                try:
                    while True:
                        await subscription.get()
                except SubscriptionClosed:
                    pass

            reader = asyncio.create_task(drain())
            await drive(worker, event_sequence(10_000))
            rows = [{"point": "start (after 10k warm-up events)", "rss_mb": rss_mb()}]
            started = time.perf_counter()
            await drive(worker, event_sequence(event_count))
            rows.append(
                {
                    "point": f"after {event_count:,} events",
                    "rss_mb": rss_mb(),
                    "seconds": time.perf_counter() - started,
                }
            )
            started = time.perf_counter()
            await run_operations(worker, operation_count)
            rows.append(
                {
                    "point": f"after {operation_count:,} operations",
                    "rss_mb": rss_mb(),
                    "seconds": time.perf_counter() - started,
                }
            )
            assert subscription.closed_reason is None, "the draining subscriber fell behind"
            reader.cancel()
    base = rows[0]["rss_mb"]
    for row in rows:
        row["growth_mb"] = round(row["rss_mb"] - base, 2)
        row["rss_mb"] = round(row["rss_mb"], 2)
        if "seconds" in row:
            row["seconds"] = round(row["seconds"], 1)
    return rows


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--events", type=int, default=1_000_000)
    parser.add_argument("--operations", type=int, default=10_000)
    parser.add_argument(
        "--cell", action="store_true", help="every process of python -m server, after --runs runs"
    )
    parser.add_argument("--runs", type=int, default=100, help="spray runs, with --cell")
    parser.add_argument(
        "--layouts", default="sim,devices", help="with --cell: sim, devices or both"
    )
    parser.add_argument(
        "--soak-minutes",
        type=float,
        default=0.0,
        help="with --cell: after the runs, go on running this long (a soak)",
    )
    parser.add_argument(
        "--every-minutes", type=float, default=5.0, help="with --soak-minutes: how often to measure"
    )
    args = parser.parse_args(argv)
    logging.disable(logging.ERROR)
    if args.cell:
        return cell_main(args.runs, args.layouts.split(","), args.soak_minutes, args.every_minutes)
    rows = asyncio.run(measure(args.events, args.operations))
    emit("memory", rows, {"target_growth_mb": 10})
    return rows


def cell_main(
    runs: int, layouts: list[str], soak_minutes: float = 0.0, every_minutes: float = 5.0
) -> list[dict[str, Any]]:
    rows = [
        row
        for layout in layouts
        for row in cell_memory.measure(layout, runs, soak_minutes, every_minutes)
    ]
    totals = cell_memory.totals(rows)
    emit(
        "memory_cell",
        rows,
        {
            "runs": runs,
            "soak_minutes": soak_minutes,
            "unique_total_mb": totals,
            "target_unique_mb": {"sim": 250, "devices": 150},
            **cell_memory.environment_note(),
        },
    )
    return rows


if __name__ == "__main__":
    main()
