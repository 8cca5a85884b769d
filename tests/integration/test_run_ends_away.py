"""A spray run ends with the arm at its safe position: the retract is the run's last
step (on record in its progress), and the inspection's frame is taken once the arm is
clear of the beads, while it still travels."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from server.core.operations.safe_position import RETRACT_STEP, clear_of
from tests.rig import SPRAY_DEMO, open_rig, run


async def test_a_run_ends_with_the_arm_at_the_safe_position(tmp_path) -> None:
    async with open_rig(tmp_path / "data") as rig:
        settings = rig.cell.settings
        seen: list[tuple[Any, bool]] = []  # the robot's position at each frame, moving or not
        capture = rig.camera.capture

        async def watched_capture() -> np.ndarray:
            seen.append((rig.robot.position, rig.robot.is_moving))
            return await capture()

        rig.camera.capture = watched_capture  # type: ignore[method-assign]
        snapshot = await run(rig, "start", SPRAY_DEMO)
        assert snapshot["state"] == "IDLE", snapshot
        assert math.dist(rig.robot.position[:3], settings.safe_position[:3]) <= 0.5
        operations = (await rig.api.get("/operations", params={"kind": "trajectory"})).json()
        latest = operations["operations"][0]
        assert latest["outcome"] == "completed"
        assert latest["progress"]["step"] == RETRACT_STEP
        assert latest["progress"]["fraction"] == 1.0
        inspection = (await rig.api.get(f"/runs/{latest['run_id']}/inspection")).json()
        assert inspection["image"] is True
        # The inspection frame: the last one the run took, with the arm clear of every bead.
        trajectory = (await rig.api.get("/trajectory")).json()
        beads = [w["pose"][:2] for w in trajectory["planned_path"] if w["spray"]]
        position, _ = seen[-1]
        assert clear_of(position, beads, settings.inspection_clearance_mm), position


async def test_the_camera_draws_the_part_while_the_arm_still_hides_it(tmp_path) -> None:
    # The simulated camera draws what it will show as the retract begins, so the frame
    # taken at the clearance waits for no drawing; the frame itself is still taken clear.
    async with open_rig(tmp_path / "data") as rig:
        clearance = rig.cell.settings.inspection_clearance_mm
        order: list[tuple[str, Any]] = []
        capture, draw_ahead = rig.camera.capture, rig.camera.draw_ahead

        async def watched_capture() -> np.ndarray:
            order.append(("capture", rig.robot.position))
            return await capture()

        async def watched_draw_ahead() -> None:
            order.append(("draw ahead", rig.robot.position))
            await draw_ahead()

        rig.camera.capture = watched_capture  # type: ignore[method-assign]
        rig.camera.draw_ahead = watched_draw_ahead  # type: ignore[method-assign]
        snapshot = await run(rig, "start", SPRAY_DEMO)
        assert snapshot["state"] == "IDLE", snapshot
        trajectory = (await rig.api.get("/trajectory")).json()
        beads = [w["pose"][:2] for w in trajectory["planned_path"] if w["spray"]]
        kinds = [kind for kind, _ in order]
        assert kinds[-2:] == ["draw ahead", "capture"], kinds
        (_, drawn_at), (_, taken_at) = order[-2:]
        assert not clear_of(drawn_at, beads, clearance), drawn_at  # the arm over the part
        assert clear_of(taken_at, beads, clearance), taken_at


async def test_with_retract_after_run_off_the_arm_stays_over_the_part(tmp_path) -> None:
    async with open_rig(tmp_path / "data", retract_after_run=False) as rig:
        snapshot = await run(rig, "start", SPRAY_DEMO)
        assert snapshot["state"] == "IDLE", snapshot
        safe = rig.cell.settings.safe_position
        assert math.dist(rig.robot.position[:3], safe[:3]) > 10


def test_clear_of_is_outside_the_beads_box_by_the_clearance() -> None:
    beads = [(350.0, -110.0), (450.0, -40.0)]
    assert not clear_of((400.0, -75.0, 50.0), beads, 30.0)  # over the part
    assert not clear_of((400.0, -20.0, 100.0), beads, 30.0)  # within the clearance
    assert clear_of((400.0, 0.0, 200.0), beads, 30.0)  # the safe position
    assert clear_of((400.0, 0.0, 200.0), [], 30.0)
