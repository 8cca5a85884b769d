"""A spray run's cycle time with and without its inspection, and the inspection's own time.

The default simulated cell (the robot and glue simulators in their thread at
real speed, the simulated camera, the commissioned demo part on the table) runs
the demo part again and again, start to back in IDLE, with inspection_enabled
switched on and off between runs (interleaved, so both see the same machine):

- `cycle`: START accepted → the cell back in IDLE, for each setting;
- `inspection`: what the inspection itself took (the frame, re-locating the
  part, the bead along every segment, the annotated JPEG), from its record.

What the plant pays for each part's verdict is the difference of the two cycle
rows; the inspection row says where it went.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.report import emit, percentiles_ms
from server.bootstrap.cell import Cell
from server.core.machine.events import StartPayload
from server.core.machine.transitions import Event, State
from server.core.worker.worker import Worker
from server.settings.model import Settings

SPRAY_FOUND_PART = StartPayload(contour_matching=True, workpiece_id="demo")


async def wait_state(worker: Worker, *states: State) -> None:
    while worker.ctx.state not in states:
        await asyncio.sleep(0.002)


async def one_cycle(cell: Cell, worker: Worker) -> tuple[float, dict[str, Any] | None]:
    """One run from START to IDLE: its duration and its inspection record (None: none)."""
    started = time.perf_counter()
    outcome = await worker.request(Event.START_REQUESTED, source="bench", payload=SPRAY_FOUND_PART)
    assert outcome.accepted, outcome.message
    await wait_state(worker, State.EXECUTING_TRAJECTORY, State.ERROR)
    await wait_state(worker, State.IDLE, State.ERROR)
    elapsed = time.perf_counter() - started
    assert worker.ctx.state is State.IDLE, f"the run ended in {worker.ctx.state}"
    journal = cell.journal
    assert journal is not None and outcome.run_id is not None
    await journal.caught_up()
    rows = journal.query("inspections", filters={"run_id": outcome.run_id}, limit=1)
    return elapsed, json.loads(rows[0]["document"]) if rows else None


async def run(runs: int) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    data = Path(tempfile.mkdtemp(prefix="bench-cycle-"))
    cell = Cell(Settings(data_path=data))
    cycles: dict[bool, list[float]] = {True: [], False: []}
    inspection_s: list[float] = []
    verdicts: dict[str, int] = {}
    try:
        await cell.start()
        worker = cell.worker
        assert worker is not None
        await wait_state(worker, State.IDLE)
        for index in range(2 * runs):
            inspecting = index % 2 == 0
            cell.settings.inspection_enabled = inspecting
            elapsed, record = await one_cycle(cell, worker)
            cycles[inspecting].append(elapsed)
            assert (record is not None) == inspecting, "inspected when off, or not when on"
            if record is not None:
                inspection_s.append(float(record["took_s"]))
                verdicts[record["verdict"]] = verdicts.get(record["verdict"], 0) + 1
    finally:
        await cell.stop()
        shutil.rmtree(data, ignore_errors=True)  # a journal and images per run: not worth keeping
    rows = [
        {"measure": "cycle, inspection on", **percentiles_ms(cycles[True])},
        {"measure": "cycle, inspection off", **percentiles_ms(cycles[False])},
        {"measure": "inspection itself", **percentiles_ms(inspection_s)},
    ]
    return rows, {"verdicts": verdicts}


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--runs", type=int, default=10, help="runs with inspection, and without")
    args = parser.parse_args(argv)
    logging.disable(logging.WARNING)
    rows, extra = asyncio.run(run(args.runs))
    emit("cycle_time", rows, {"runs": args.runs, **extra})
    return rows


if __name__ == "__main__":
    main()
