"""Workpiece outlines, poses and library matching against the simulator's ground truth.

The pipeline is the cell's: raw frame → undistort → markers (excluded) → find_outlines →
outline_to_mm through the table calibration → match_outline. Claims: area centroid within
1 mm and rotation within 1° (modulo the part's symmetry) for several shapes and turns.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from server.drivers.sim.camera_model import DEFAULT_CAMERA_MODEL
from server.drivers.sim.camera_scene import WORKPIECE_SHAPES, Scene, render_table
from server.vision.homography import fit_plane_calibration
from server.vision.intrinsics import Undistorter, intrinsics_of
from server.vision.markers import MarkerDetector
from server.vision.outlines import (
    OutlineMatch,
    find_outlines,
    match_outline,
    outline_pose,
    outline_to_mm,
    polygon_area_centroid,
    transform_outline,
)

MODEL = DEFAULT_CAMERA_MODEL
EXCLUSION_SCALE = 1.8  # marker square → its paper sheet with margin (what the cell uses)
LIBRARY = {name: np.asarray(shape.outline_mm) for name, shape in WORKPIECE_SHAPES.items()}


@pytest.fixture(scope="module")
def undistorter() -> Undistorter:
    return Undistorter(intrinsics_of(MODEL.camera_matrix, MODEL.dist_coeffs, MODEL.size))


@pytest.fixture(scope="module")
def homography(undistorter: Undistorter) -> np.ndarray:
    scene = Scene()
    frame = undistorter(render_table(scene, rng=np.random.default_rng(21)))
    detections = MarkerDetector(fast=False).detect(frame)
    robot_mm = dict(enumerate(scene.marker_positions_mm))
    return fit_plane_calibration({i: d.centre for i, d in detections.items()}, robot_mm).homography


def outlines_mm(scene: Scene, undistorter: Undistorter, homography: np.ndarray) -> list[np.ndarray]:
    frame = undistorter(render_table(scene, rng=np.random.default_rng(5)))
    exclude = [
        d.centre + (d.corners - d.centre) * EXCLUSION_SCALE
        for d in MarkerDetector().detect(frame).values()
    ]
    return [outline_to_mm(c, homography) for c in find_outlines(frame, exclude=exclude)]


def turn_error(measured: float, true: float, symmetry_deg: float) -> float:
    """Smallest difference between two turns, modulo the part's symmetry."""
    period = symmetry_deg if symmetry_deg > 0 else 360.0
    diff = (measured - true) % period
    return min(diff, period - diff)


CASES = [
    ("rect-120x80", 400.0, -300.0, 0.4),
    ("rect-120x80", 150.0, 0.0, 90.0),
    ("rect-120x80", 400.0, 300.0, 179.0),
    ("l-bracket", 650.0, 0.0, 0.0),
    ("l-bracket", 400.0, -300.0, 90.0),
    ("l-bracket", 150.0, 20.0, 179.0),
    ("l-bracket", 400.0, 300.0, -135.0),
    ("hexagon", 150.0, -20.0, 10.0),
    ("square-60", 650.0, 300.0, 44.0),
    ("rounded-rect-100x60", 650.0, -300.0, 91.0),
    ("disc-70", 650.0, 0.0, 0.0),
]


@pytest.mark.parametrize(("name", "x", "y", "turn"), CASES)
def test_a_placed_workpiece_is_found_where_it_lies(
    name: str, x: float, y: float, turn: float, undistorter: Undistorter, homography: np.ndarray
) -> None:
    scene = Scene()
    piece = scene.place_workpiece(name, x, y, turn)
    found = outlines_mm(scene, undistorter, homography)
    assert len(found) == 1
    outline = found[0]
    pose = outline_pose(outline)
    assert math.hypot(pose.x - x, pose.y - y) < 1.0
    area, _ = polygon_area_centroid(outline)
    assert area == pytest.approx(piece.shape.area_mm2, rel=0.02)  # and counter-clockwise

    match = match_outline(outline, LIBRARY)
    assert isinstance(match, OutlineMatch)
    assert match.workpiece_id == name
    assert match.score < 0.03
    assert match.fit_error_mm < 0.3
    if piece.shape.symmetry_deg > 0:  # a disc has no turn to find
        assert turn_error(match.rotation_deg, turn, piece.shape.symmetry_deg) < 1.0
    # the library outline is centred on the origin: it moves to the part's centroid
    assert math.hypot(match.translation_mm[0] - x, match.translation_mm[1] - y) < 1.0
    placed = transform_outline(LIBRARY[name], match.transform)
    _, centroid = polygon_area_centroid(placed)
    assert math.hypot(centroid[0] - x, centroid[1] - y) < 1.0


def test_a_rectangle_turned_by_179_degrees_is_reported_as_minus_1(
    undistorter: Undistorter, homography: np.ndarray
) -> None:
    """180° symmetry: both answers fit equally; the smaller turn is the one returned."""
    scene = Scene()
    scene.place_workpiece("rect-120x80", 400.0, 300.0, 179.0)
    match = match_outline(outlines_mm(scene, undistorter, homography)[0], LIBRARY)
    assert match is not None
    assert match.rotation_deg == pytest.approx(-1.0, abs=1.0)


def test_a_taught_outline_is_followed_to_its_new_pose(
    undistorter: Undistorter, homography: np.ndarray
) -> None:
    """The library holds outlines as detected when taught (not at the origin)."""
    taught_scene = Scene()
    taught_scene.place_workpiece("l-bracket", 150.0, 0.0, 20.0)
    taught = outlines_mm(taught_scene, undistorter, homography)[0]
    scene = Scene()
    scene.place_workpiece("l-bracket", 400.0, -300.0, 125.0)
    detected = outlines_mm(scene, undistorter, homography)[0]
    match = match_outline(detected, {"bracket": taught, "plate": LIBRARY["rect-120x80"]})
    assert match is not None and match.workpiece_id == "bracket"
    assert turn_error(match.rotation_deg, 105.0, 360.0) < 1.0
    assert math.hypot(match.translation_mm[0] - 250.0, match.translation_mm[1] + 300.0) < 1.0
    moved = transform_outline(taught, match.transform)
    _, centroid = polygon_area_centroid(moved)
    assert math.hypot(centroid[0] - 400.0, centroid[1] + 300.0) < 1.0


def test_library_shapes_are_told_apart(undistorter: Undistorter, homography: np.ndarray) -> None:
    scene = Scene()
    placed = {
        "rect-120x80": (400.0, -300.0, 30.0),
        "l-bracket": (400.0, 300.0, 60.0),
        "hexagon": (150.0, -20.0, 5.0),
        "disc-70": (650.0, 0.0, 0.0),
        "square-60": (150.0, 300.0, 10.0),
        "rounded-rect-100x60": (650.0, -300.0, 45.0),
    }
    for name, (x, y, turn) in placed.items():
        scene.place_workpiece(name, x, y, turn)
    found = outlines_mm(scene, undistorter, homography)
    assert len(found) == len(placed)
    seen = set()
    for outline in found:
        pose = outline_pose(outline)
        truth = min(placed, key=lambda n: math.hypot(placed[n][0] - pose.x, placed[n][1] - pose.y))
        match = match_outline(outline, LIBRARY)
        assert match is not None and match.workpiece_id == truth
        others = {k: v for k, v in LIBRARY.items() if k != truth}
        runner_up = match_outline(outline, others, max_score=10.0)
        assert runner_up is not None and runner_up.score > 3 * match.score + 0.05
        assert match_outline(outline, others) is None  # nothing else passes the default
        seen.add(truth)
    assert seen == set(placed)


def test_outlines_come_largest_first_and_skip_markers_only_when_told(
    undistorter: Undistorter,
) -> None:
    scene = Scene()
    scene.place_workpiece("square-60", 650.0, 0.0)
    scene.place_workpiece("rect-120x80", 400.0, -300.0)
    frame = undistorter(render_table(scene, rng=np.random.default_rng(1)))
    everything = find_outlines(frame)
    assert len(everything) == 2 + 9  # the nine marker sheets are bright too
    detections = MarkerDetector().detect(frame)
    exclude = [d.centre + (d.corners - d.centre) * EXCLUSION_SCALE for d in detections.values()]
    parts = find_outlines(frame, exclude=exclude)
    assert len(parts) == 2
    areas = [abs(polygon_area_centroid(p)[0]) for p in parts]
    assert areas[0] > areas[1]
    assert all(p.ndim == 2 and p.shape[1] == 2 and p.dtype == np.float64 for p in parts)


def test_a_part_cut_by_the_image_border_is_ignored(undistorter: Undistorter) -> None:
    scene = Scene()
    corner = MODEL.pixel_to_table(np.array([5.0, 540.0]))  # on the image's left edge
    scene.place_workpiece("rect-120x80", float(corner[0]), float(corner[1]), 0.0)
    frame = render_table(scene, rng=np.random.default_rng(1))
    detections = MarkerDetector().detect(frame)
    exclude = [d.centre + (d.corners - d.centre) * EXCLUSION_SCALE for d in detections.values()]
    assert find_outlines(frame, exclude=exclude) == []


def test_an_empty_table_has_no_outlines() -> None:
    frame = render_table(Scene(), rng=np.random.default_rng(1))
    detections = MarkerDetector().detect(frame)
    exclude = [d.centre + (d.corners - d.centre) * EXCLUSION_SCALE for d in detections.values()]
    assert find_outlines(frame, exclude=exclude) == []
    assert find_outlines(np.full((1080, 1920, 3), 66, dtype=np.uint8)) == []


def test_outline_to_mm_is_open_and_counter_clockwise() -> None:
    # a square traced clockwise in pixels with a dense staircase-free outline
    side = np.linspace(0.0, 100.0, 51)[:-1]
    square = np.concatenate(
        [
            np.stack([side, np.zeros_like(side)], 1),
            np.stack([np.full_like(side, 100.0), side], 1),
            np.stack([100.0 - side, np.full_like(side, 100.0)], 1),
            np.stack([np.zeros_like(side), 100.0 - side], 1),
        ]
    )
    mirror = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # swaps x and y
    outline = outline_to_mm(square, mirror)
    assert len(outline) == 4
    assert polygon_area_centroid(outline)[0] == pytest.approx(10000.0)
    assert not np.allclose(outline[0], outline[-1])


def test_outline_pose_of_a_turned_rectangle() -> None:
    shape = np.array([[-50.0, -20.0], [50.0, -20.0], [50.0, 20.0], [-50.0, 20.0]])
    a = math.radians(30.0)
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    pose = outline_pose(shape @ rot.T + (300.0, -40.0))
    assert pose.x == pytest.approx(300.0) and pose.y == pytest.approx(-40.0)
    assert pose.theta_deg == pytest.approx(30.0)
    assert outline_pose((shape @ rot.T)[::-1]).theta_deg == pytest.approx(30.0)  # clockwise too


def test_transform_outline_applies_a_rigid_transform() -> None:
    transform = np.array([[0.0, -1.0, 10.0], [1.0, 0.0, 5.0]])  # +90° then shift
    moved = transform_outline(np.array([[1.0, 0.0], [0.0, 2.0]]), transform)
    np.testing.assert_allclose(moved, [[10.0, 6.0], [8.0, 5.0]])


def test_match_needs_an_outline() -> None:
    assert match_outline(np.zeros((2, 2)), LIBRARY) is None
    assert match_outline(LIBRARY["hexagon"], {}) is None
