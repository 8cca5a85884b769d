"""Each defect injected in the simulators is caught by the run's inspection; a clean run
is good (docs/quality.md).

A real server on the rig's simulators, the robot at the speed the plan says (so the glue
the run needs is the glue it should get), the simulated camera drawing the bead the
simulators actually laid. The inspection sees only its frame, the plan and the devices'
readings: nothing here tells it what was injected.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from typing import Any

import pytest

from tests.rig import SPRAY_DEMO, WAIT_S, Rig, open_rig, run

pytestmark = pytest.mark.asyncio


async def inspected_run(
    rig: Rig, while_spraying: Callable[[], Awaitable[None] | None] | None = None
) -> dict[str, Any]:
    """Start the demo part's run, do `while_spraying` once glue flows; its inspection."""
    started = await rig.api.post("/start", json=SPRAY_DEMO)
    assert started.status_code == 202, started.text
    if while_spraying is not None:
        async with asyncio.timeout(WAIT_S):
            while not rig.glue.valve_open:
                await asyncio.sleep(0.005)
        done = while_spraying()
        if done is not None:
            await done
    async with asyncio.timeout(WAIT_S):
        while (await rig.state())["state"] not in ("IDLE", "ERROR"):
            await asyncio.sleep(0.05)
    state = await rig.state()
    assert state["state"] == "IDLE", state
    run_id = started.json()["run_id"]
    response = await rig.api.get(f"/runs/{run_id}/inspection")
    assert response.status_code == 200, response.text
    return response.json()


def said(inspection: dict[str, Any], *words: str) -> bool:
    """Whether one of the inspection's reasons holds every word."""
    return any(all(w in reason for w in words) for reason in inspection["reasons"])


async def test_a_clean_run_is_good_and_its_image_is_kept(tmp_path) -> None:
    async with open_rig(tmp_path, robot_speed_factor=1) as rig:
        inspection = await inspected_run(rig)
        assert (inspection["verdict"], inspection["reasons"]) == ("good", [])
        assert inspection["vision"]["residual_mean_mm"] < 0.2
        assert all(s["width_mean_mm"] for s in inspection["segments"])
        image = await rig.api.get(f"/runs/{inspection['run_id']}/inspection.jpg")
        assert image.status_code == 200 and image.content[:2] == b"\xff\xd8"


async def test_a_partly_clogged_nozzle_is_caught(tmp_path) -> None:
    async with open_rig(tmp_path, robot_speed_factor=1) as rig:
        # 15 % less glue: under the dispenser's own FLOW_DEVIATION alarm (20 %), so the
        # run completes, and only its inspection can tell the part is short of glue.
        rig.glue.clog_nozzle(0.85)
        inspection = await inspected_run(rig)
        assert inspection["verdict"] == "defective"
        assert said(inspection, "flow") or said(inspection, "glue"), inspection["reasons"]
        assert inspection["dispensing"]["cv_percent"] is not None


async def test_a_valve_that_opens_late_leaves_a_gap(tmp_path) -> None:
    async with open_rig(tmp_path, robot_speed_factor=1) as rig:
        rig.glue.delay_valve(150)
        inspection = await inspected_run(rig)
        assert inspection["verdict"] == "defective"
        assert said(inspection, "gap"), inspection["reasons"]
        assert max(s["longest_gap_mm"] for s in inspection["segments"]) > 3.0


async def test_a_part_shifted_after_matching_is_caught(tmp_path) -> None:
    async with open_rig(tmp_path, robot_speed_factor=1) as rig:
        inspection = await inspected_run(rig, lambda: rig.camera.shift_part(3.0, 0.0))
        assert inspection["verdict"] == "defective"
        assert said(inspection, "moved"), inspection["reasons"]
        [part] = inspection["vision"]["parts"]
        assert part["moved_mm"] == pytest.approx(3.0, abs=0.4)
        assert said(inspection, "off its planned path"), inspection["reasons"]


async def test_a_camera_knocked_by_2_mm_shows_in_the_residual_and_warns(tmp_path) -> None:
    async with open_rig(tmp_path, robot_speed_factor=1) as rig:
        rig.camera.knock(2.0, 0.0)
        inspection = await inspected_run(rig)
        assert inspection["vision"]["residual_mean_mm"] == pytest.approx(2.0, abs=0.5)
        assert inspection["verdict"] == "defective", inspection
        # Drifting calibration warned of, on record, before it spoils parts.
        warned = await rig.api.get("/errors", params={"code": "CALIBRATION_DEGRADING"})
        assert warned.status_code == 200, warned.text
        [warning] = warned.json()["errors"]
        assert warning["classification"] == "warning"
        assert inspection["run_id"] in warning["message"]


# Parts and poses between the marker rows, each taught from the camera with its bead set
# in from the edge; one with a raster fill as well.
CLEAN_PARTS = [
    ("l-bracket", 400.0, -75.0, 10.0, {"outline_offset_mm": -6.0}),
    ("hexagon", 330.0, 75.0, 90.0, {"outline_offset_mm": -5.0}),
    ("disc-70", 480.0, 75.0, 0.0, {"outline_offset_mm": -5.0}),
    (
        "rect-120x80",
        400.0,
        75.0,
        -8.0,
        {"outline_offset_mm": -5.0, "fill": "raster", "fill_spacing_mm": 20.0},
    ),
]


async def test_clean_runs_on_other_parts_and_poses_are_good(tmp_path) -> None:
    async with open_rig(tmp_path, robot_speed_factor=1) as rig:
        for shape, x, y, rotation, spray in CLEAN_PARTS:
            rig.camera.clear_workpieces()
            rig.camera.place_workpiece(shape, x, y, rotation)
            taught = await run(
                rig, "create-workpiece", {"name": shape, "workpiece_id": shape, "spray": spray}
            )
            assert taught["state"] == "IDLE", taught["error"]
            started = await rig.api.post(
                "/start", json={"contour_matching": True, "workpiece_id": shape}
            )
            assert started.status_code == 202, started.text
            await rig.wait_state("EXECUTING_TRAJECTORY")
            await rig.wait_state("IDLE", timeout=WAIT_S * 2)
            run_id = started.json()["run_id"]
            inspection = (await rig.api.get(f"/runs/{run_id}/inspection")).json()
            assert inspection["verdict"] == "good", (shape, inspection["reasons"])
