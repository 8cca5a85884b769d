"""A spray run's cycle time with and without its inspection and its retract.

The default simulated cell (the robot and glue simulators in their thread at
real speed, the simulated camera, the commissioned demo part on the table) runs
the demo part again and again, start to back in IDLE, in four modes: neither
(inspection_enabled and retract_after_run off), the retract alone, the
inspection alone, and both (the default). Each mode runs a block of runs in a
row and its first run is left out, so every run measured begins where the
previous run of its own mode left the arm (at the safe position after a
retract, over the last bead without one: the run's first step then travels to
the safe position). The blocks go round the modes in turn, so all see the same
machine. Before each run a fresh part is laid where the last one was (what an
order does between its parts), so each frame shows one part's bead.

- `cycle`: START accepted → the cell back in IDLE, for each mode;
- `inspection`: what the inspection itself took (from its frame on: re-locating
  the part, the bead along every segment, the annotated JPEG), from its record;
- `step: ...`: the p50 of each step of a run's end, in the modes that inspect
  (bench/cycle_steps.py says what each step is), to show where the time goes.

`--busy` measures the runs with a busy loop on every core at the default priority
(bench/busy.py), as another job on the same machine would keep them; the cell
starts and commissions itself before they start.

`both / neither` is what a verdict and an arm out of the way cost the plant per
part: the retract replaces the next run's first travel, and the inspection takes
its frame as soon as the arm is clear of the beads and does its work while the arm
travels on (server/core/operations/safe_position.py).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import shutil
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.busy import busy_loop_on_every_core
from bench.cycle_steps import STEP_ORDER, StepClock
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


async def one_cycle(
    cell: Cell, worker: Worker, clock: StepClock, mode: str | None
) -> tuple[float, dict[str, Any] | None]:
    """One run from START to IDLE: its duration and its inspection record (None: none);
    its steps go to `clock` under `mode` (None: not measured)."""
    present_next_part = getattr(cell.devices.camera, "present_next_part", None)
    if present_next_part is not None:
        present_next_part()  # each run sprays a fresh part, as an order's runs do
    clock.begin_run()
    started = time.perf_counter()
    outcome = await worker.request(Event.START_REQUESTED, source="bench", payload=SPRAY_FOUND_PART)
    assert outcome.accepted, outcome.message
    await wait_state(worker, State.EXECUTING_TRAJECTORY, State.ERROR)
    await wait_state(worker, State.IDLE, State.ERROR)
    idle_at = time.perf_counter()
    elapsed = idle_at - started
    clock.end_run(idle_at, mode)
    assert worker.ctx.state is State.IDLE, f"the run ended in {worker.ctx.state}"
    journal = cell.journal
    assert journal is not None and outcome.run_id is not None
    await journal.caught_up()
    rows = journal.query("inspections", filters={"run_id": outcome.run_id}, limit=1)
    return elapsed, json.loads(rows[0]["document"]) if rows else None


MODES = {  # name: (inspection_enabled, retract_after_run)
    "neither": (False, False),
    "retract": (False, True),
    "inspection": (True, False),
    "both": (True, True),
}


async def run(
    runs: int, block: int, busy: bool = False
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    data = Path(tempfile.mkdtemp(prefix="bench-cycle-"))
    cell = Cell(Settings(data_path=data))
    cycles: dict[str, list[float]] = {mode: [] for mode in MODES}
    inspection_s: list[float] = []
    verdicts: dict[str, int] = {}
    try:
        await cell.start()
        worker = cell.worker
        assert worker is not None
        await wait_state(worker, State.IDLE)
        clock = StepClock(cell.devices.camera, cell.stores.inspection_images)
        loaded = busy_loop_on_every_core() if busy else contextlib.nullcontext()
        with clock, loaded:
            await measure(cell, worker, clock, runs, block, cycles, inspection_s, verdicts)
    finally:
        await cell.stop()
        shutil.rmtree(data, ignore_errors=True)  # a journal and images per run: not worth keeping
    rows = [
        {"measure": f"cycle, {mode}", **percentiles_ms(samples)} for mode, samples in cycles.items()
    ]
    rows.append({"measure": "inspection itself", **percentiles_ms(inspection_s)})
    for mode in ("inspection", "both"):
        steps = clock.samples[mode]
        for step in STEP_ORDER:
            if steps.get(step):
                rows.append({"measure": f"step ({mode}): {step}", **percentiles_ms(steps[step])})
    neither = statistics.median(cycles["neither"])
    ratio = {
        f"{mode} / neither": round(statistics.median(samples) / neither, 4)
        for mode, samples in cycles.items()
        if mode != "neither"
    }
    return rows, {"verdicts": verdicts, "p50_ratios": ratio}


async def measure(
    cell: Cell,
    worker: Worker,
    clock: StepClock,
    runs: int,
    block: int,
    cycles: dict[str, list[float]],
    inspection_s: list[float],
    verdicts: dict[str, int],
) -> None:
    """Blocks of runs, the modes in turn, until each mode has `runs` measured."""
    while min(len(c) for c in cycles.values()) < runs:
        for mode, (inspecting, retracting) in MODES.items():
            cell.settings.inspection_enabled = inspecting
            cell.settings.retract_after_run = retracting
            for index in range(block + 1):
                measured = mode if index > 0 else None  # the first began where another left
                elapsed, record = await one_cycle(cell, worker, clock, measured)
                assert (record is not None) == inspecting, "inspected when off, or not on"
                if measured is None:
                    continue
                cycles[mode].append(elapsed)
                if record is not None:
                    inspection_s.append(float(record["took_s"]))
                    verdicts[record["verdict"]] = verdicts.get(record["verdict"], 0) + 1


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--runs", type=int, default=10, help="runs measured in each mode")
    parser.add_argument("--block", type=int, default=2, help="runs in a row in one mode")
    parser.add_argument(
        "--busy", action="store_true", help="the runs beside a busy loop on every core"
    )
    parser.add_argument("--name", default="cycle_time", help="the result file's name")
    args = parser.parse_args(argv)
    logging.disable(logging.WARNING)
    rows, extra = asyncio.run(run(args.runs, args.block, args.busy))
    emit(args.name, rows, {"runs": args.runs, "block": args.block, "busy": args.busy, **extra})
    for name, value in extra["p50_ratios"].items():
        print(f"{name}: {value:.3f} (p50)")
    return rows


if __name__ == "__main__":
    main()
