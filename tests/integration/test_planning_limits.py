"""Path planning bounded and cancellable, through the whole server on the real simulators.

The issue's part: an 800-point outline with a 1 mm fill. The library refuses it at
edit (422 naming the field); a file stored before the limits still plans, but a run
gives up at planning_timeout with PLANNING_TIMEOUT before any motion along the path,
and a cancel or an e-stop stops the planning itself, so repeated start/cancel cycles
leave no work behind and the library and history keep answering.
"""

from __future__ import annotations

import asyncio
import math

import numpy as np

from server.storage.workpieces import (
    MAX_FILL_LINES,
    MAX_FILL_STROKES,
    MAX_OUTLINE_POINTS,
    SpraySettings,
    WorkpieceIn,
)
from tests.rig import Rig, open_rig, run

HEAVY = {"contour_matching": False, "workpiece_id": "heavy"}


def gear(points: int, radius: float = 300.0) -> list[list[float]]:
    """A toothed outline (teeth 15 % deep) centred at (450, 0) mm."""
    t = np.linspace(0.0, 2 * math.pi, points, endpoint=False)
    r = radius * (1 + 0.15 * np.where(np.arange(points) % 2 == 0, 1.0, -1.0))
    return [
        [450.0 + float(a * math.cos(b)), float(a * math.sin(b))] for a, b in zip(r, t, strict=True)
    ]


def store_heavy_part(rig: Rig) -> None:
    """The issue's part, as a file stored before the edit limits existed."""
    old = WorkpieceIn.model_construct(
        name="heavy",
        outline_mm=[tuple(p) for p in gear(800)],
        spray=SpraySettings(fill="zigzag", fill_spacing_mm=1.0),
    )
    assert rig.cell.stores is not None
    rig.cell.stores.workpieces.put("heavy", old)


async def planning_begun(rig: Rig, runs: int) -> None:
    """The `runs`-th run has moved to the safe position: what follows is its planning."""
    safe = tuple(rig.cell.settings.safe_position)
    async with asyncio.timeout(15):
        while sum(tuple(s.end) == safe for s in rig.robot.executed_path) < runs:
            await asyncio.sleep(0.005)
    await asyncio.sleep(0.05)


async def test_a_part_too_complex_to_plan_is_refused_at_edit_naming_the_field(tmp_path) -> None:
    async with open_rig(tmp_path) as rig:
        issue = {
            "name": "gear",
            "outline_mm": gear(800),
            "spray": {"fill": "zigzag", "fill_spacing_mm": 1},
        }
        refused = await rig.api.post("/workpieces", json=issue)
        assert refused.status_code == 422, refused.text
        assert refused.json()["errors"][0]["field"] == "outline_mm"
        assert str(MAX_OUTLINE_POINTS) in refused.json()["detail"]
        # Few enough points, but a fill of too many lines: the spacing that would do.
        wide = {**issue, "outline_mm": [[0, -1500], [1500, -1500], [1500, 1500], [0, 1500]]}
        refused = await rig.api.post("/workpieces", json=wide)
        assert refused.status_code == 422, refused.text
        assert refused.json()["errors"][0]["field"] == "spray"
        detail = refused.json()["detail"]
        assert "fill_spacing_mm 1 gives 3000 fill lines" in detail and str(MAX_FILL_LINES) in detail
        assert "at least 3.0 mm" in detail
        # Few lines, but each crosses the teeth many times: too many strokes.
        toothed = {**issue, "outline_mm": gear(MAX_OUTLINE_POINTS, 200.0)}
        toothed["spray"] = {"fill": "zigzag", "fill_spacing_mm": 2}
        refused = await rig.api.put("/workpieces/demo", json=toothed)
        assert refused.status_code == 422, refused.text
        assert "fill strokes" in refused.json()["detail"]
        assert str(MAX_FILL_STROKES) in refused.json()["detail"]
        # The same outline at the spacing the message names is accepted.
        toothed["spray"] = {"fill": "zigzag", "fill_spacing_mm": 10}
        accepted = await rig.api.post("/workpieces", json=toothed)
        assert accepted.status_code == 201, accepted.text
        assert (await rig.api.get("/workpieces/demo")).json()["spray"]["fill"] != "zigzag"


async def test_a_plan_past_planning_timeout_fails_the_run_before_any_motion(tmp_path) -> None:
    async with open_rig(tmp_path, planning_timeout=0.2) as rig:
        store_heavy_part(rig)
        rig.robot.clear_path()
        snapshot = await run(rig, "start", HEAVY)
        assert snapshot["state"] == "ERROR"
        assert snapshot["error"]["code"] == "PLANNING_TIMEOUT", snapshot["error"]
        assert "planning_timeout" in snapshot["error"]["message"]
        safe = tuple(rig.cell.settings.safe_position)
        assert [s for s in rig.robot.executed_path if tuple(s.end) != safe] == []
        assert rig.glue.valve_open is False


async def test_cancel_and_estop_stop_the_planning_and_other_requests_still_answer(
    tmp_path,
) -> None:
    # A planning thread left running for minutes after each cancel would fill the
    # default thread pool after seven, and GET /workpieces and /history would time out.
    async with open_rig(tmp_path) as rig:
        store_heavy_part(rig)
        rig.robot.clear_path()
        for cycle in range(7):
            assert (await rig.api.post("/start", json=HEAVY)).status_code == 202
            await planning_begun(rig, cycle + 1)
            if cycle == 6:
                assert (await rig.api.post("/estop")).status_code == 202
                await rig.wait_state("ERROR")
                assert (await rig.reset()).status_code == 202
            else:
                assert (await rig.api.post("/cancel")).status_code == 202
            await rig.wait_state("IDLE")
            listed = await rig.api.get("/workpieces")
            assert listed.status_code == 200
            assert "heavy" in {w["id"] for w in listed.json()["workpieces"]}
            assert (await rig.api.get("/history")).status_code == 200
        # Nothing moved along the path in any of the seven runs.
        safe = tuple(rig.cell.settings.safe_position)
        assert [s for s in rig.robot.executed_path if tuple(s.end) != safe] == []
