"""Journal write throughput and the latency it adds to a command, per synchronous level.

1. Throughput: events appended as fast as the loop can (one event record each,
   as the worker writes them), until all are committed; group commit batches
   whatever is queued into one transaction.
2. Added latency: a refused command (`resume` in IDLE: decided at once, no
   device I/O) from request to answer, with no journal (baseline) and with the
   journal at each `journal_synchronous` level; the answer waits until its
   event is committed.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.engine_throughput import NullDevice, NullJournal
from bench.report import emit, percentiles_ms
from server.core.infra.bus import Bus
from server.core.machine.transitions import Event, State
from server.core.operations import default_operations
from server.core.worker.devices import CellDevices
from server.core.worker.worker import Worker
from server.settings.model import Settings
from server.storage import CellStores
from server.storage.journal import Journal, records

LEVELS = ("OFF", "NORMAL", "FULL")


async def throughput(level: str, count: int, directory: Path) -> float:
    journal = Journal(directory / f"throughput-{level}.db", synchronous=level)
    journal.open()
    journal.start(asyncio.get_running_loop())
    started = time.perf_counter()
    futures = [
        journal.append(
            [
                records.event(
                    f"e{i}", time.time(), "PAUSE_REQUESTED", "bench", {}, "refused", "bench", "IDLE"
                )
            ]
        )
        for i in range(count)
    ]
    await asyncio.gather(*futures)
    elapsed = time.perf_counter() - started
    journal.stop()
    return count / elapsed


async def command_latency(level: str | None, trials: int, directory: Path) -> list[float]:
    journal: Journal | NullJournal = NullJournal()
    if level is not None:
        journal = Journal(directory / f"latency-{level}.db", synchronous=level)
        journal.open()
        journal.start(asyncio.get_running_loop())
    devices = CellDevices(NullDevice("robot"), NullDevice("glue"), NullDevice("camera"))  # type: ignore[arg-type]
    worker = Worker(
        Settings(data_path=directory),
        devices,
        default_operations(),
        Bus(),
        CellStores.open(directory / "stores"),
        journal=journal,  # type: ignore[arg-type]
    )
    await worker.start()
    while worker.ctx.state is not State.IDLE:
        await asyncio.sleep(0.001)
    samples = []
    for _ in range(trials):
        started = time.perf_counter()
        await worker.request(Event.RESUME_REQUESTED, source="bench")
        samples.append(time.perf_counter() - started)
    await worker.stop()
    if isinstance(journal, Journal):
        journal.stop()
    return samples


async def run(count: int, trials: int) -> list[dict[str, Any]]:
    rows = []
    with tempfile.TemporaryDirectory() as name:
        directory = Path(name)
        baseline = percentiles_ms(await command_latency(None, trials, directory))
        rows.append(
            {
                "journal_synchronous": "no journal",
                "events_per_s": None,
                "command_p50_ms": baseline["p50_ms"],
                "command_p99_ms": baseline["p99_ms"],
                "added_p50_ms": 0.0,
            }
        )
        for level in LEVELS:
            rate = await throughput(level, count, directory)
            latency = percentiles_ms(await command_latency(level, trials, directory))
            rows.append(
                {
                    "journal_synchronous": level,
                    "events_per_s": round(rate),
                    "command_p50_ms": latency["p50_ms"],
                    "command_p99_ms": latency["p99_ms"],
                    "added_p50_ms": round(latency["p50_ms"] - baseline["p50_ms"], 3),
                }
            )
    return rows


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--events", type=int, default=50_000)
    parser.add_argument("--trials", type=int, default=500)
    args = parser.parse_args(argv)
    logging.disable(logging.ERROR)
    rows = asyncio.run(run(args.events, args.trials))
    emit("journal", rows, {"events": args.events, "trials": args.trials})
    return rows


if __name__ == "__main__":
    main()
