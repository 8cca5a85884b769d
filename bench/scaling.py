"""How latency and memory grow with queue depth, WebSocket clients and journal size.

Three sweeps, each a table, drawn together in bench/results/scaling.png:

- queue depth: the request lane filled with d requests (refused ones: a pause
  in IDLE), then one more request and an e-stop. Measured: the time the last
  request waits for its answer (it is behind d others: expected to grow
  linearly), the e-stop's time to its decision (its own lane: expected flat),
  and resident memory with the queue full. Server as in bench/memory.py:
  production persistence, no-op devices, in this process.
- WebSocket clients: the fan-out of a transition to N clients, from
  bench/ws_fanout.py (server in its own process), with the server's resident
  memory once the N clients are connected.
- journal size: the journal prefilled with n event records, then the time
  from a command (a refused `resume`, no device I/O) to its durable answer,
  and resident memory; a full journal must not slow the cell down (appends
  are O(1); retention and queries use indexes).
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from bench import ws_fanout
from bench.engine_throughput import NullDevice
from bench.memory import done_at_once, rss_mb
from bench.report import emit, percentiles_ms, results_path
from server.bootstrap.cell import Cell
from server.core.machine.transitions import Event, State
from server.core.worker.devices import CellDevices
from server.core.worker.worker import Worker
from server.settings.model import Settings
from server.storage.journal import Journal, records

REPEATS = 20  # per point of the queue-depth sweep
PREFILL_BATCH = 5000


def null_cell(data_path: Path, **settings: Any) -> Cell:
    devices = CellDevices(NullDevice("robot"), NullDevice("glue"), NullDevice("camera"))  # type: ignore[arg-type]
    operations = dict.fromkeys(
        ("trajectory", "calibrate_robot", "calibrate_camera", "create_workpiece"), done_at_once
    )
    return Cell(
        Settings(data_path=data_path, commission_simulated_cell=False, **settings),
        devices=devices,
        operations=operations,
    )


async def started(cell: Cell) -> Worker:
    await cell.start()
    assert cell.worker is not None
    while cell.worker.ctx.state is not State.IDLE:
        await asyncio.sleep(0.01)
    return cell.worker


async def queue_depth_point(worker: Worker, depth: int, repeats: int = REPEATS) -> dict[str, Any]:
    waits, stops, memory = [], [], []
    for _ in range(repeats):
        if worker.ctx.state is State.ERROR:
            await worker.request(Event.RESET_REQUESTED, source="bench")
        while worker.ctx.state is not State.IDLE:
            await asyncio.sleep(0.001)
        queued = [worker.submit(Event.PAUSE_REQUESTED, source="bench") for _ in range(depth)]
        memory.append(rss_mb())
        sent = time.perf_counter()
        last = worker.submit(Event.PAUSE_REQUESTED, source="bench")
        await worker.stops.stop(source="bench")
        stops.append(time.perf_counter() - sent)
        assert last.future is not None
        await last.future
        waits.append(time.perf_counter() - sent)
        await asyncio.gather(*(e.future for e in queued if e.future is not None))
    return {
        "queue_depth": depth,
        "last_request_p50_ms": percentiles_ms(waits)["p50_ms"],
        "estop_decided_p50_ms": percentiles_ms(stops)["p50_ms"],
        "estop_decided_p99_ms": percentiles_ms(stops)["p99_ms"],
        "estop_decided_max_ms": percentiles_ms(stops)["max_ms"],
        "repeats": repeats,
        "rss_mb": round(statistics.median(memory), 1),
    }


async def queue_depth_sweep(depths: list[int], repeats: int = REPEATS) -> list[dict[str, Any]]:
    with tempfile.TemporaryDirectory() as directory:
        cell = null_cell(Path(directory), event_queue_size=max(depths) + 10)
        worker = await started(cell)
        try:
            return [await queue_depth_point(worker, depth, repeats) for depth in depths]
        finally:
            await cell.stop()


def prefill(path: Path, count: int) -> None:
    """`count` event records, written as the worker writes them, in big transactions."""
    journal = Journal(path, synchronous="OFF")
    journal.open()
    loop = asyncio.new_event_loop()
    journal.start(loop)
    now = time.time()
    for first in range(0, count, PREFILL_BATCH):
        batch = [
            records.event(
                f"prefill-{i:08d}",
                now,
                Event.RESUME_REQUESTED.value,
                "bench",
                {},
                "refused",
                "resume is not allowed in IDLE",
                State.IDLE.value,
            )
            for i in range(first, min(count, first + PREFILL_BATCH))
        ]
        future = journal.append(batch)
        assert future is not None
        loop.run_until_complete(future)
    journal.stop()
    loop.close()


async def journal_size_point(size: int, requests: int) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as directory:
        data = Path(directory)
        await asyncio.to_thread(prefill, data / "journal.db", size)
        cell = null_cell(data)
        opened = time.perf_counter()
        worker = await started(cell)
        start_up = time.perf_counter() - opened
        samples = []
        try:
            for _ in range(requests):
                sent = time.perf_counter()
                outcome = await worker.request(Event.RESUME_REQUESTED, source="bench")
                samples.append(time.perf_counter() - sent)
                assert not outcome.accepted
            memory = rss_mb()
        finally:
            await cell.stop()
        figures = percentiles_ms(samples)
        return {
            "journal_events": size,
            "command_p50_ms": figures["p50_ms"],
            "command_p99_ms": figures["p99_ms"],
            "start_up_s": round(start_up, 2),
            "rss_mb": round(memory, 1),
        }


async def journal_size_sweep(sizes: list[int], requests: int) -> list[dict[str, Any]]:
    return [await journal_size_point(size, requests) for size in sizes]


def websocket_sweep(counts: list[int], transitions: int) -> list[dict[str, Any]]:
    rows = ws_fanout.main(
        [
            "--clients",
            ",".join(map(str, counts)),
            "--transitions",
            str(transitions),
            "--name",
            "scaling_ws_fanout",
        ]
    )
    return [
        {
            "ws_clients": row["clients"],
            "fanout_p50_ms": row["p50_ms"],
            "fanout_p99_ms": row["p99_ms"],
            "server_rss_mb": row.get("server_rss_mb"),
        }
        for row in rows
    ]


def plot(
    depth: list[dict[str, Any]], clients: list[dict[str, Any]], journal: list[dict[str, Any]]
) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    panels = (
        (
            axes[0],
            depth,
            "queue_depth",
            "requests queued",
            [
                ("last_request_p50_ms", "last request answered (p50)"),
                ("estop_decided_p50_ms", "e-stop decided (p50)"),
            ],
        ),
        (
            axes[1],
            clients,
            "ws_clients",
            "WebSocket clients",
            [
                ("fanout_p50_ms", "fan-out p50"),
                ("fanout_p99_ms", "fan-out p99"),
            ],
        ),
        (
            axes[2],
            journal,
            "journal_events",
            "events in the journal",
            [
                ("command_p50_ms", "command answered, durable (p50)"),
                ("command_p99_ms", "command answered, durable (p99)"),
            ],
        ),
    )
    for axis, rows, x_key, x_label, series in panels:
        xs = [max(row[x_key], 1) for row in rows]
        for key, label in series:
            axis.plot(xs, [row[key] for row in rows], marker="o", label=label)
        axis.set_xscale("log")
        axis.set_xlabel(f"{x_label} (log scale; 0 drawn at 1)")
        axis.set_ylabel("latency (ms)")
        axis.set_ylim(bottom=0)
        memory_key = "server_rss_mb" if x_key == "ws_clients" else "rss_mb"
        if all(row.get(memory_key) is not None for row in rows):
            twin = axis.twinx()
            memory = [row[memory_key] for row in rows]
            twin.plot(xs, memory, "k--", marker="s", label="RSS")
            twin.set_ylabel("resident memory (MB)")
            twin.set_ylim(0, max(memory) * 1.2)  # from zero: a small wobble is not growth
            twin.legend(loc="lower right", fontsize=8)
        axis.legend(loc="upper left", fontsize=8)
        axis.grid(True, alpha=0.3)
    figure.suptitle("Scaling: latency (lines) and resident memory (dashed)")
    figure.tight_layout()
    path = results_path("scaling.png")
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


def main(argv: list[str] | None = None) -> dict[str, list[dict[str, Any]]]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--depths", default="0,10,100,1000,10000")
    parser.add_argument(
        "--depth-repeats", type=int, default=REPEATS, help="e-stops per queue depth"
    )
    parser.add_argument("--clients", default="10,100,1000")
    parser.add_argument("--journal-sizes", default="0,10000,100000,1000000")
    parser.add_argument("--requests", type=int, default=300, help="commands per journal size")
    parser.add_argument("--transitions", type=int, default=100, help="per WebSocket point")
    args = parser.parse_args(argv)
    logging.disable(logging.ERROR)
    as_ints = lambda text: [int(part) for part in text.split(",")]  # noqa: E731
    depth = asyncio.run(queue_depth_sweep(as_ints(args.depths), args.depth_repeats))
    journal = asyncio.run(journal_size_sweep(as_ints(args.journal_sizes), args.requests))
    clients = websocket_sweep(as_ints(args.clients), args.transitions)
    emit("scaling_queue_depth", depth)
    emit("scaling_journal_size", journal)
    emit("scaling_ws_clients", clients)
    print(f"plot: {plot(depth, clients, journal)}")
    return {"queue_depth": depth, "ws_clients": clients, "journal_size": journal}


if __name__ == "__main__":
    main()
