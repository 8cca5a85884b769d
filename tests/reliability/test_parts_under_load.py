"""The simulated cell judges clean parts good however busy the machine is.

A run stretched by load (the robot's answers late, the valve open while the arm
waits for its next move) once dispensed glue for the wall time the valve stood
open, so a newcomer on a busy laptop saw clean parts judged defective on glue
volume. The simulated dispenser follows the robot's speed, as a real
speed-following dispenser does: no glue leaves while the arm stands still.

Nor does load fault the cell or leave a part uninspected: the image process works
only a little below the server (server/vision/process.py, NICE). At the lowest
priority, a busy loop per core left it so little of a core that the default cell's
frames missed vision_processing_timeout: VISION_TIMEOUT, or "not inspected".

The default simulated cell (simulators in their thread at real speed, the demo
part, every setting at its default), with a busy loop on every core in processes
this test starts and ends.
"""

from __future__ import annotations

import asyncio
import json
import os

import pytest

from bench.busy import busy_loop_on_every_core
from server.bootstrap.cell import Cell
from server.core.machine.events import StartPayload
from server.core.machine.transitions import Event, State
from server.settings.model import Settings

PARTS = int(os.environ.get("PARTS_UNDER_LOAD", 10))
SPRAY_DEMO = StartPayload(contour_matching=False, workpiece_id="demo")
WAIT_S = 600.0  # a bound on a run on a machine kept busy on purpose, not a figure


async def until(cell: Cell, *states: State) -> None:
    assert cell.worker is not None
    async with asyncio.timeout(WAIT_S):
        while cell.worker.ctx.state not in states:
            await asyncio.sleep(0.02)


@pytest.mark.whole_machine
async def test_ten_clean_parts_are_good_with_every_core_busy(tmp_path) -> None:
    cell = Cell(Settings(data_path=tmp_path / "data"))  # the default cell, its bounds too
    await cell.start()
    try:
        await until(cell, State.IDLE)
        assert cell.worker is not None and cell.journal is not None
        verdicts = []
        with busy_loop_on_every_core():
            for _ in range(PARTS):
                outcome = await cell.worker.request(
                    Event.START_REQUESTED, source="test", payload=SPRAY_DEMO
                )
                assert outcome.accepted, outcome.message
                await until(cell, State.EXECUTING_TRAJECTORY, State.ERROR)
                await until(cell, State.IDLE, State.ERROR)
                assert cell.worker.ctx.state is State.IDLE, cell.worker.ctx.stop_reason
                await cell.journal.caught_up()
                rows = cell.journal.query(
                    "inspections", filters={"run_id": outcome.run_id}, limit=1
                )
                document = json.loads(rows[0]["document"])
                glue = document["dispensing"]["glue_ratio_percent"]
                verdicts.append((document["verdict"], glue, document["reasons"]))
        assert [verdict for verdict, _, _ in verdicts] == ["good"] * PARTS, verdicts
    finally:
        await cell.stop()
