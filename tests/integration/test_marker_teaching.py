"""Marker positions taught with the robot: the jog, the draft layout, apply, calibration.

Real simulators (tests/rig.py): the robot simulator moves, the camera shows the
simulated table whose markers sit on the default grid.
"""

from __future__ import annotations

import asyncio
import math
import stat

import numpy as np
import pytest

from server.settings.model import DEFAULT_MARKER_POSITIONS_MM
from tests.rig import WAIT_S, Rig, open_rig

FAST_JOG = {"jog_speed_mm_s": 250.0, "jog_max_step_mm": 150.0}


async def settled(rig: Rig) -> tuple[float, float, float]:
    """The simulated tool's x, y, z once no move is under way."""
    async with asyncio.timeout(WAIT_S):
        while True:
            layout = (await rig.api.get("/calibration/markers")).json()
            if not layout["robot"]["moving"] and not rig.robot.is_moving:
                return tuple(rig.robot.position[:3])  # type: ignore[return-value]
            await asyncio.sleep(0.01)


async def jog(rig: Rig, axis: str, distance: float) -> dict:
    response = await rig.api.post("/jog", json={"axis": axis, "distance_mm": distance})
    assert response.status_code == 202, response.text
    await settled(rig)
    return response.json()


async def jog_to(rig: Rig, x: float, y: float) -> None:
    """Jog in steps no longer than the cap until the tool is over (x, y)."""
    for axis, index, goal in (("x", 0, x), ("y", 1, y)):
        while abs(gap := goal - (await settled(rig))[index]) > 1e-6:
            await jog(rig, axis, max(-150.0, min(150.0, gap)))


async def test_a_jog_moves_the_robot_by_its_step_and_nothing_else(tmp_path) -> None:
    async with open_rig(tmp_path / "data", **FAST_JOG) as rig:
        x, y, z = await settled(rig)
        answer = await jog(rig, "x", 12.5)
        assert answer["state"] == "IDLE"
        assert (await settled(rig)) == pytest.approx((x + 12.5, y, z), abs=0.01)

        too_long = await rig.api.post("/jog", json={"axis": "y", "distance_mm": 150.5})
        assert too_long.status_code == 422, too_long.text
        assert too_long.json()["errors"][0]["field"] == "distance_mm"
        assert "jog_max_step_mm" in too_long.json()["detail"]

        await jog_to(rig, 700.0, y)  # 800 mm is the workspace's x limit
        before = await settled(rig)
        outside = await rig.api.post("/jog", json={"axis": "x", "distance_mm": 150.0})
        assert outside.status_code == 422, outside.text
        assert outside.json()["errors"][0]["field"] == "distance_mm"
        assert "outside the workspace" in outside.json()["detail"]
        wrong_axis = await rig.api.post("/jog", json={"axis": "rx", "distance_mm": 1.0})
        assert wrong_axis.status_code == 422 and "axis" in wrong_axis.json()["detail"]
        nothing = await rig.api.post("/jog", json={"axis": "x", "distance_mm": 0})
        assert nothing.status_code == 422 and "0 mm moves nothing" in nothing.json()["detail"]
        assert (await settled(rig)) == pytest.approx(before, abs=0.01)
        assert (await rig.state())["state"] == "IDLE"

        created = await rig.api.post("/tokens", json={"name": "op", "role": "operator"})
        operator = {"Authorization": f"Bearer {created.json()['token']}"}
        denied = await rig.api.post(
            "/jog", json={"axis": "x", "distance_mm": -1.0}, headers=operator
        )
        assert denied.status_code == 403
        denied = await rig.api.post("/calibration/markers/draft/0/teach", headers=operator)
        assert denied.status_code == 403

        assert (await rig.api.post("/estop")).status_code == 202
        await rig.wait_state("ERROR")
        refused = await rig.api.post("/jog", json={"axis": "x", "distance_mm": -10.0})
        assert refused.status_code == 409, refused.text
        assert "ERROR" in refused.json()["message"]
        assert (await settled(rig)) == pytest.approx(before, abs=0.01)
        assert (await rig.state())["state"] == "ERROR"

        audit = (await rig.api.get("/audit", params={"action": "POST /jog"})).json()["audit"]
        outcomes = sorted(row["outcome"] for row in audit)
        assert outcomes.count("accepted") >= 2 and "refused (409)" in outcomes
        events = (await rig.api.get("/events", params={"limit": 1000})).json()
        jogs = [e for e in events["events"] if e["type"] == "JOG_REQUESTED"]
        assert len(jogs) >= 4  # each jog, accepted or refused by the cell, is journaled


async def test_a_robot_fault_during_a_jog_ends_safe(tmp_path) -> None:
    async with open_rig(tmp_path / "data", jog_speed_mm_s=5.0) as rig:
        await settled(rig)
        response = await rig.api.post("/jog", json={"axis": "z", "distance_mm": -40.0})
        assert response.status_code == 202, response.text
        async with asyncio.timeout(WAIT_S):
            while not rig.robot.is_moving:
                await asyncio.sleep(0.005)
        rig.robot.inject_fault("drop")
        snapshot = await rig.wait_state("ERROR")
        assert snapshot["stop_reason"]["component"] == "robot"
        assert not rig.glue.valve_open
        async with asyncio.timeout(WAIT_S):
            while rig.robot.is_moving:
                await asyncio.sleep(0.01)


async def test_an_incomplete_or_invalid_layout_is_refused_naming_the_marker(tmp_path) -> None:
    async with open_rig(tmp_path / "data") as rig:
        in_force = (await rig.api.get("/calibration/markers")).json()["in_force"]
        missing = await rig.api.post("/calibration/markers/apply")
        assert missing.status_code == 409
        assert [e["field"] for e in missing.json()["errors"]] == [f"markers.{i}" for i in range(9)]
        for i, (x, y) in enumerate(DEFAULT_MARKER_POSITIONS_MM):
            typed = {"x_mm": 900.0 if i == 7 else x, "y_mm": y}
            response = await rig.api.put(f"/calibration/markers/draft/{i}", json=typed)
            assert response.status_code == 200, response.text
        refused = await rig.api.post("/calibration/markers/apply")
        assert refused.status_code == 409, refused.text
        assert refused.json()["errors"][0]["field"] == "markers.7"
        assert "marker 7" in refused.json()["detail"] and "workspace" in refused.json()["detail"]
        # Every marker at fault at once: it named only the first.
        for i, (x, y) in ((0, (50.0, -150.0)), (5, (410.0, 10.0))):
            typed = await rig.api.put(
                f"/calibration/markers/draft/{i}", json={"x_mm": x, "y_mm": y}
            )
            assert typed.status_code == 200, typed.text
        refused = await rig.api.post("/calibration/markers/apply")
        fields = [e["field"] for e in refused.json()["errors"]]
        assert fields == ["markers.0", "markers.7", "markers.4"], refused.json()
        bad_marker = await rig.api.put("/calibration/markers/draft/9", json={"x_mm": 1, "y_mm": 1})
        assert bad_marker.status_code == 422 and "marker" in bad_marker.json()["detail"]
        bad_value = await rig.api.put("/calibration/markers/draft/3", json={"x_mm": "1", "y_mm": 1})
        assert bad_value.status_code == 422 and "x_mm" in bad_value.json()["detail"]
        after = (await rig.api.get("/calibration/markers")).json()
        assert after["in_force"] == in_force and after["source"] == "settings"
        assert after["draft"][7]["x_mm"] == 900.0  # the draft is kept to be corrected
        draft_file = tmp_path / "data" / "calibration" / "markers.json"
        assert stat.S_IMODE(draft_file.stat().st_mode) == 0o600


async def test_a_taught_layout_is_applied_and_used_by_the_robot_calibration(tmp_path) -> None:
    """Teach each marker 5 mm off in x: the new calibration maps to the taught layout."""
    async with open_rig(tmp_path / "data", **FAST_JOG) as rig:
        old = rig.cell.stores.calibration.robot
        assert old is not None  # the commissioned cell's, on the default layout
        shifted = [(x + 5.0, y) for x, y in DEFAULT_MARKER_POSITIONS_MM]
        for i, (x, y) in enumerate(shifted):
            await jog_to(rig, x, y)
            taught = await rig.api.post(f"/calibration/markers/draft/{i}/teach")
            assert taught.status_code == 200, taught.text
            entry = taught.json()["draft"][i]
            assert (entry["x_mm"], entry["y_mm"], entry["how"]) == (
                pytest.approx(x, abs=0.01),
                pytest.approx(y, abs=0.01),
                "taught",
            )
        applied = await rig.api.post("/calibration/markers/apply")
        assert applied.status_code == 200, applied.text
        body = applied.json()
        assert body["source"] == "taught" and body["missing"] == []
        assert body["in_force"] == [
            [pytest.approx(x, abs=0.01), pytest.approx(y)] for x, y in shifted
        ]
        audit = await rig.api.get("/audit", params={"action": "POST /calibration/markers/apply"})
        assert "taught layout applied" in audit.json()["audit"][0]["detail"]

        snapshot = await rig.api.post("/calibrate-robot")
        assert snapshot.status_code == 202, snapshot.text
        await asyncio.sleep(0)
        async with asyncio.timeout(WAIT_S):
            while (state := await rig.state())["state"] != "IDLE":
                assert state["state"] != "ERROR", state
                await asyncio.sleep(0.02)
        new = rig.cell.stores.calibration.robot
        assert new is not None and new is not old
        # Where the camera sees marker 4 maps to where it was taught, not where it was before.
        pixel = old.to_pixels(np.array([[400.0, 0.0]]))
        mapped = new.to_robot(pixel)[0]
        assert math.dist(mapped, (405.0, 0.0)) < 0.5, mapped
