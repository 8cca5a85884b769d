"""What the flight recorder costs in the journal: bytes per run with run_recording on and off.

The default simulated cell (robot and glue simulators at real speed, the
commissioned demo part) sprays the demo part again and again, start to back in
IDLE, with `run_recording` switched on and off between runs (interleaved, so
both see the same machine). After each run, once the journal is caught up, the
bytes the journal's rows take in SQLite's pages (`dbstat`: every table and
index, what is in the WAL included, each page's unused bytes left out, so the
figure is not rounded to whole 4 KiB pages) are read; a run's cost is the
growth across it.

Rows: journal bytes per run (median, and the spread as min and max) for each
setting, the samples a run recorded, and the run's length. The JSON adds the
bytes per sample and the growth of an 8-hour shift of back-to-back runs (the
recording's share and the whole), the figure docs/kpis.md quotes.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import shutil
import sqlite3
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.cycle_time import wait_state
from bench.report import emit
from server.bootstrap.cell import Cell
from server.core.machine.events import StartPayload
from server.core.machine.transitions import Event, State
from server.settings.model import Settings

SPRAY_DEMO = StartPayload(contour_matching=False, workpiece_id="demo")
SHIFT_S = 8 * 3600.0


def journal_bytes(path: Path) -> int:
    """The bytes used in the pages of every table and index of the journal (the WAL's too)."""
    connection = sqlite3.connect(path)
    try:
        return int(connection.execute("SELECT SUM(pgsize - unused) FROM dbstat").fetchone()[0])
    finally:
        connection.close()


def samples_of(path: Path, run_id: str) -> int:
    connection = sqlite3.connect(path)
    try:
        query = "SELECT COUNT(*) FROM run_samples WHERE run_id = ?"
        return int(connection.execute(query, (run_id,)).fetchone()[0])
    finally:
        connection.close()


async def run(runs: int) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    data = Path(tempfile.mkdtemp(prefix="bench-recording-"))
    cell = Cell(Settings(data_path=data))
    grown: dict[bool, list[int]] = {True: [], False: []}
    seconds: list[float] = []
    samples: list[int] = []
    try:
        await cell.start()
        worker, journal = cell.worker, cell.journal
        assert worker is not None and journal is not None
        await wait_state(worker, State.IDLE)
        for index in range(2 * runs):
            recording = index % 2 == 0
            cell.settings.run_recording = recording
            assert cell.recorder is not None
            cell.recorder.settings = cell.settings.section(type(cell.recorder.settings))
            await journal.caught_up()
            before = await asyncio.to_thread(journal_bytes, journal.path)
            started = time.perf_counter()
            outcome = await worker.request(
                Event.START_REQUESTED, source="bench", payload=SPRAY_DEMO
            )
            assert outcome.accepted and outcome.run_id is not None, outcome.message
            await wait_state(worker, State.EXECUTING_TRAJECTORY, State.ERROR)
            await wait_state(worker, State.IDLE, State.ERROR)
            assert worker.ctx.state is State.IDLE, f"the run ended in {worker.ctx.state}"
            elapsed = time.perf_counter() - started
            cell.recorder.flush()
            await journal.caught_up()
            after = await asyncio.to_thread(journal_bytes, journal.path)
            grown[recording].append(after - before)
            if recording:
                seconds.append(elapsed)
                samples.append(await asyncio.to_thread(samples_of, journal.path, outcome.run_id))
    finally:
        await cell.stop()
        shutil.rmtree(data, ignore_errors=True)

    def row(measure: str, values: list[int] | list[float], unit: str) -> dict[str, Any]:
        return {
            "measure": measure,
            "unit": unit,
            "median": round(statistics.median(values), 1),
            "min": round(min(values), 1),
            "max": round(max(values), 1),
        }

    on, off = statistics.median(grown[True]), statistics.median(grown[False])
    per_run_s = statistics.median(seconds)
    runs_per_shift = SHIFT_S / per_run_s
    rows = [
        row("journal bytes per run, recording on", grown[True], "B"),
        row("journal bytes per run, recording off", grown[False], "B"),
        row("samples per run", samples, "rows"),
        row("run length", seconds, "s"),
    ]
    extra = {
        "bytes_per_sample": round((on - off) / statistics.median(samples), 1),
        "runs_per_8h_shift_back_to_back": round(runs_per_shift),
        "shift_bytes_recording_on": round(on * runs_per_shift),
        "shift_bytes_recording_off": round(off * runs_per_shift),
    }
    return rows, extra


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--runs", type=int, default=5, help="runs recorded, and not")
    args = parser.parse_args(argv)
    logging.disable(logging.WARNING)
    rows, extra = asyncio.run(run(args.runs))
    emit("recording_cost", rows, {"runs": args.runs, **extra})
    return rows


if __name__ == "__main__":
    main()
