"""The four operations through the whole server, checked against the simulated
camera's ground truth: calibration to 0.5 mm, focal length to 2 %, workpiece
position to 1 mm and rotation to 1°, the executed path equal to the planned
one, and a part outside the workspace refused before any motion."""

from __future__ import annotations

import math
from collections.abc import AsyncIterator

import cv2
import numpy as np
import pytest

from server.drivers.sim.camera_scene import Scene
from server.settings.model import DEFAULT_MARKER_POSITIONS_MM as GRID
from server.vision.homography import pixels_to_robot
from tests.rig import Rig, open_rig, run


@pytest.fixture
async def rig(tmp_path) -> AsyncIterator[Rig]:
    async with open_rig(tmp_path) as running:
        yield running


async def test_robot_calibration_maps_every_marker_within_half_a_millimetre(rig: Rig) -> None:
    snapshot = await run(rig, "calibrate-robot")
    assert snapshot["state"] == "IDLE", snapshot["error"]
    calibration = (await rig.api.get("/calibration")).json()["robot"]
    assert calibration["mean_error_mm"] < 0.5 and calibration["max_error_mm"] < 0.5
    assert calibration["created_at"] > 0
    # Checked independently of the fit: its scale against the printed marker side, and each
    # marker predicted by a map fitted without it.
    assert abs(calibration["scale_error_pct"]) < 0.2, calibration
    assert calibration["holdout_max_error_mm"] < 0.5, calibration
    # Independently of the fit's own residuals: where the camera truly sees each
    # marker centre, through the stored undistortion and map, back to the robot.
    camera, store = rig.camera, rig.cell.stores.calibration
    positions = np.asarray(rig.cell.settings.marker_positions_mm, dtype=np.float64)
    true_pixels = camera.model.project(np.column_stack([positions, np.zeros(9)]))
    from server.vision.intrinsics import Undistorter

    undistorted = Undistorter(store.camera).points(true_pixels)
    mapped = pixels_to_robot(np.asarray(calibration["homography"]), undistorted)
    errors = np.linalg.norm(mapped - positions, axis=1)
    assert errors.max() < 0.5, errors
    image = await rig.api.get("/calibration/image")
    assert image.status_code == 200 and image.headers["content-type"] == "image/png"
    assert cv2.imdecode(np.frombuffer(image.content, np.uint8), cv2.IMREAD_COLOR).shape[1] == 1920


async def test_camera_calibration_recovers_the_focal_length(rig: Rig) -> None:
    snapshot = await run(rig, "calibrate-camera")
    assert snapshot["state"] == "IDLE", snapshot["error"]
    camera = (await rig.api.get("/calibration")).json()["camera"]
    fx, fy = camera["camera_matrix"][0][0], camera["camera_matrix"][1][1]
    assert fx == pytest.approx(rig.camera.model.fx, rel=0.02)
    assert fy == pytest.approx(rig.camera.model.fy, rel=0.02)
    assert rig.camera.mode == "table"  # the simulated operator put the board away
    # A new camera calibration makes the old robot calibration stale: refused before it
    # starts (409, still IDLE), not misused and not a fault.
    refused = await rig.api.post("/create-workpiece")
    assert refused.status_code == 409 and "run calibrate-robot again" in refused.json()["message"]
    assert (await rig.api.get("/state")).json()["state"] == "IDLE"


async def test_camera_calibration_waits_between_views_for_the_board_to_move(tmp_path) -> None:
    async with open_rig(tmp_path, camera_calibration_view_interval_s=0.05) as rig:
        progress = rig.cell.bus.subscribe(maxsize=10_000, types=["progress"])
        snapshot = await run(rig, "calibrate-camera")
        assert snapshot["state"] == "IDLE", snapshot["error"]
        steps = []
        while progress.pending:
            steps.append((await progress.get()).data.get("step"))
        prompts = steps.count("move the chessboard to a new pose")
        assert prompts >= rig.cell.settings.camera_calibration_views - 1, steps


# Poses between the marker rows (the papers span y = ±22 and ±128..172 mm).
@pytest.mark.parametrize(
    ("shape", "x", "y", "rotation", "move"),
    [
        ("rect-120x80", 400.0, 75.0, 0.0, (-15.0, 0.0, 8.0)),
        ("l-bracket", 400.0, -75.0, 0.0, (-10.0, -3.0, 10.0)),
        ("hexagon", 330.0, 75.0, 90.0, (-15.0, 0.0, 12.0)),
    ],
)
async def test_a_created_workpiece_is_found_again_where_it_lies(rig, shape, x, y, rotation, move):
    camera = rig.camera
    camera.clear_workpieces()
    placed = camera.place_workpiece(shape, x, y, rotation)
    snapshot = await run(rig, "create-workpiece", {"name": shape, "workpiece_id": "part"})
    assert snapshot["state"] == "IDLE", snapshot["error"]
    stored = (await rig.api.get("/workpieces/part")).json()
    outline = np.asarray(stored["outline_mm"], dtype=np.float32)
    moments = cv2.moments(outline)
    centroid = (moments["m10"] / moments["m00"], moments["m01"] / moments["m00"])
    assert math.dist(centroid, placed.centroid_table_mm()) < 1.0
    thumbnail = await rig.api.get("/workpieces/part/thumbnail")
    assert thumbnail.status_code == 200

    # Move the part: contour matching finds it, with the right displacement and turn.
    camera.clear_workpieces()
    dx, dy, turn = move
    moved = camera.place_workpiece(shape, x + dx, y + dy, rotation + turn)
    rig.robot.clear_path()
    snapshot = await run(rig, "start", {"contour_matching": True, "workpiece_id": "part"})
    assert snapshot["state"] == "IDLE", snapshot["error"]
    trajectory = (await rig.api.get("/trajectory")).json()
    match = trajectory["workpieces"][0]["match"]
    rotation_error = (match["rotation_deg"] - turn + 180.0) % 60.0  # hexagon: 60° symmetry
    if shape != "hexagon":
        rotation_error = (match["rotation_deg"] - turn + 180.0) % 360.0 - 180.0
    else:
        rotation_error = min(rotation_error, 60.0 - rotation_error)
    assert abs(rotation_error) < 1.0, match
    # The library outline moved by the match lands on the part's true outline.
    planned_xy = np.asarray([w["pose"][:2] for w in trajectory["planned_path"] if w["spray"]])
    true_outline = moved.outline_table_mm().astype(np.float32)
    distances = [
        abs(cv2.pointPolygonTest(true_outline, (float(px), float(py)), True))
        for px, py in planned_xy
    ]
    assert max(distances) < 1.0, max(distances)
    # And the robot simulator executed exactly the planned path, after the run's first
    # step: the move to the safe position.
    executed = [s.end for s in rig.robot.executed_path if s.method == "moveL"]
    assert list(executed[0]) == pytest.approx(list(rig.cell.settings.safe_position), abs=0.01)
    executed = executed[1:]
    planned = [w["pose"] for w in trajectory["planned_path"]]
    assert len(executed) >= len(planned)
    for reached, target in zip(executed, planned, strict=False):
        assert list(reached) == pytest.approx(target, abs=0.01)


async def test_a_part_partly_outside_the_workspace_is_refused_before_any_motion(tmp_path):
    # The workspace must hold every marker (a setting checked at load), so the part is moved
    # beyond the markers, across the workspace's edge at x = 660 mm.
    async with open_rig(tmp_path, workspace_max_mm=(660.0, 400.0, 500.0)) as rig:
        rig.camera.clear_workpieces()
        rig.camera.place_workpiece("rect-120x80", 650.0, 0.0, 5.0)
        rig.robot.clear_path()
        snapshot = await run(rig, "start")
        assert snapshot["state"] == "ERROR"
        assert snapshot["error"]["code"] == "WORKSPACE_VIOLATION"
        assert "waypoint" in snapshot["error"]["message"] and "x=" in snapshot["error"]["message"]
        # No move towards the part at all (only the homing to the safe position, if any).
        safe = tuple(rig.cell.settings.safe_position)
        assert [s for s in rig.robot.executed_path if tuple(s.end) != safe] == []
        assert rig.glue.valve_open is False


async def test_a_table_printed_at_another_scale_is_refused_and_the_map_kept(rig: Rig) -> None:
    before = (await rig.api.get("/calibration")).json()["robot"]
    rig.camera.scene = Scene.printed(rig.cell.settings.marker_positions_mm, 30.0, scale=1.02)
    snapshot = await run(rig, "calibrate-robot")
    assert snapshot["state"] == "ERROR"
    error = snapshot["error"]
    assert error["code"] == "CALIBRATION_SCALE", error
    # the measured numbers and the limit: 30 mm markers read as 30 / 1.02 = 29.41 mm
    assert "off by -1.9" in error["message"] and "limit 1 %" in error["message"], error
    assert "29.4" in error["message"] and "marker_size_mm is 30 mm" in error["message"], error
    assert (await rig.api.get("/calibration")).json()["robot"] == before


async def test_a_moved_marker_is_refused_by_the_holdout_and_the_map_kept(rig: Rig) -> None:
    before = (await rig.api.get("/calibration")).json()["robot"]
    x, y = rig.camera.scene.marker_positions_mm[4]
    rig.camera.scene.marker_positions_mm[4] = (x + 2.0, y)  # bumped on the table
    snapshot = await run(rig, "calibrate-robot")
    assert snapshot["state"] == "ERROR"
    error = snapshot["error"]
    assert error["code"] == "CALIBRATION_HOLDOUT", error
    assert "hold-out error 2.0" in error["message"] and "exceeds 1 mm" in error["message"], error
    assert "without marker 4" in error["message"], error
    assert (await rig.api.get("/calibration")).json()["robot"] == before


async def test_the_simulated_table_is_printed_from_the_configured_layout(tmp_path) -> None:
    # Not the simulator's grid, nor any projective image of it (the map would absorb that).
    layout = [(x + 15.0 if y > 0 else x, y) for x, y in GRID]
    layout[4] = (420.0, 10.0)
    async with open_rig(tmp_path, marker_positions_mm=layout, marker_size_mm=36.0) as rig:
        # commissioning calibrated the robot against this layout and this marker size
        robot = (await rig.api.get("/calibration")).json()["robot"]
        assert robot is not None and robot["mean_error_mm"] < 0.5, robot
        assert abs(robot["scale_error_pct"]) < 0.2 and robot["holdout_max_error_mm"] < 0.5


async def test_a_covered_marker_fails_calibration_naming_it(rig: Rig) -> None:
    rig.camera.place_workpiece("rect-120x80", 400.0, 0.0, 0.0)  # right over marker 4
    snapshot = await run(rig, "calibrate-robot")
    assert snapshot["state"] == "ERROR"
    assert snapshot["error"]["code"] == "MARKER_NOT_FOUND"
    assert snapshot["error"]["message"].startswith("marker 4 not found")


async def test_the_workpiece_library_over_http(rig: Rig) -> None:
    api = rig.api
    body = {
        "name": "plate",
        "outline_mm": [[300, -50], [420, -50], [420, 30], [300, 30]],
        "spray": {"fill": "zigzag", "fill_spacing_mm": 20, "outline_offset_mm": -5},
    }
    created = await api.post("/workpieces", json=body)
    assert created.status_code == 201
    workpiece_id = created.json()["id"]
    assert (await api.get(f"/workpieces/{workpiece_id}")).json()["spray"]["fill"] == "zigzag"
    ids = [w["id"] for w in (await api.get("/workpieces")).json()["workpieces"]]
    assert {"demo", workpiece_id} <= set(ids)
    body["name"] = "plate v2"
    replaced = await api.put(f"/workpieces/{workpiece_id}", json=body)
    assert replaced.json()["name"] == "plate v2"
    assert replaced.json()["created_at"] == created.json()["created_at"]
    # Spray it as stored: outline 5 mm inside, then a zigzag fill.
    rig.robot.clear_path()
    snapshot = await run(rig, "start", {"contour_matching": False, "workpiece_id": workpiece_id})
    assert snapshot["state"] == "IDLE", snapshot["error"]
    assert (await api.delete(f"/workpieces/{workpiece_id}")).status_code == 204
    assert (await api.get(f"/workpieces/{workpiece_id}")).status_code == 404
    assert (await api.delete(f"/workpieces/{workpiece_id}")).status_code == 404
    bad = await api.post("/workpieces", json={"name": "x", "outline_mm": [[0, 0], [1, 1]]})
    assert bad.status_code == 422 and "outline_mm" in bad.json()["detail"]
    bad = await api.put("/workpieces/..%2Fetc", json=body)
    assert bad.status_code in (404, 422)
    # An unknown part is refused before the run starts (409), not a fault.
    unknown = await api.post("/start", json={"contour_matching": False, "workpiece_id": "nope"})
    assert (
        unknown.status_code == 409 and "'nope' is not in the library" in unknown.json()["message"]
    )
    assert (await api.get("/state")).json()["state"] == "IDLE"
