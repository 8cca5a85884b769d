"""The simulated camera is only useful if its ground truth is exact and its images realistic.

These tests hold the renderer to what the vision code will later be held to: markers found by
OpenCV at their true centres, chessboard corners at their true pixels and a calibration that
recovers the true focal length, and workpiece outlines that map back to their true positions.
"""

from __future__ import annotations

import dataclasses
import logging

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from server.common.runtime import MMAP_THRESHOLD
from server.drivers.sim import camera_model
from server.drivers.sim.camera_model import DEFAULT_CAMERA_MODEL, CameraModel
from server.drivers.sim.camera_scene import (
    DEFAULT_CHESSBOARD,
    WORKPIECE_SHAPES,
    Scene,
    Workpiece,
    aruco_dictionary,
    chessboard_corner_pixels,
    default_chessboard_poses,
    marker_centre_pixels,
    marker_corners_mm,
    polygon_area_centroid,
    polygon_coverage,
    render_chessboard_view,
    render_table,
    workpiece_outline_pixels,
)

MODEL = DEFAULT_CAMERA_MODEL


def diagonal_intersection(corners: np.ndarray) -> np.ndarray:
    """Centre of a quadrilateral as the crossing of its diagonals (exact under perspective)."""
    p0, p1, p2, p3 = corners
    a = np.column_stack([p2 - p0, p1 - p3])
    s, _ = np.linalg.solve(a, p1 - p0)
    return p0 + s * (p2 - p0)


# --- the camera model --------------------------------------------------------------------


def test_project_matches_opencv() -> None:
    rng = np.random.default_rng(1)
    points = np.column_stack(
        [rng.uniform(100, 700, 500), rng.uniform(-500, 500, 500), rng.uniform(-20, 50, 500)]
    )
    expected, _ = cv2.projectPoints(
        points, np.array(MODEL.rvec), np.array(MODEL.tvec), MODEL.camera_matrix, MODEL.dist_coeffs
    )
    assert np.abs(MODEL.project(points) - expected.reshape(-1, 2)).max() < 1e-8


@settings(max_examples=60, deadline=None)
@given(
    x=st.floats(80.0, 720.0),
    y=st.floats(-550.0, 550.0),
    z=st.sampled_from([0.0, 12.5]),
)
def test_pixel_to_table_round_trip(x: float, y: float, z: float) -> None:
    pixel = MODEL.table_to_pixel(np.array([x, y]), z_mm=z)
    back = MODEL.pixel_to_table(pixel, z_mm=z)
    assert np.abs(back - (x, y)).max() < 1e-6


def test_round_trip_from_pixels_over_the_whole_image() -> None:
    u, v = np.meshgrid(np.linspace(0, 1919, 40), np.linspace(0, 1079, 25))
    pixels = np.stack([u, v], axis=-1)
    assert np.abs(MODEL.table_to_pixel(MODEL.pixel_to_table(pixels)) - pixels).max() < 1e-8


@pytest.mark.parametrize("block", [1, 777, 1 << 13])
def test_undistortion_does_not_depend_on_its_block_size(
    block: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Blocks of points take the same Newton steps as the whole array in one: the rays of a
    frame's pixels are the same to the bit, whether centre pixels (met in few steps) and
    corner ones share a block or not."""
    strong = dataclasses.replace(MODEL, dist=(-0.3, 0.1, 0.001, -0.002, 0.02))
    u, v = np.meshgrid(np.linspace(0, 1919, 97), np.linspace(0, 1079, 61))
    pixels = np.stack([u, v], axis=-1)
    monkeypatch.setattr(camera_model, "NEWTON_BLOCK", pixels.size)  # one block: the whole
    whole = strong.pixel_to_normalised(pixels)
    monkeypatch.setattr(camera_model, "NEWTON_BLOCK", block)
    assert np.array_equal(strong.pixel_to_normalised(pixels), whole)
    seen = np.stack([(u - strong.cx) / strong.fx, (v - strong.cy) / strong.fy], axis=-1)
    assert np.abs(strong.distort(whole) - seen).max() < 1e-14


def test_the_undistortions_temporaries_come_from_the_heap() -> None:
    """Below the mmap threshold the server and its image process fix: above it, each of a
    Newton step's temporaries is mapped and faulted in anew (three times the arithmetic)."""
    assert camera_model.NEWTON_BLOCK * np.dtype(np.float64).itemsize < MMAP_THRESHOLD


def test_default_model_sees_markers_and_the_work_area_around_them() -> None:
    papers = np.vstack(list(marker_corners_mm(Scene(), paper=True).values()))
    assert MODEL.sees(np.column_stack([papers, np.zeros(len(papers))]), margin_px=50).all()
    x, y = np.meshgrid(np.linspace(150, 650, 21), np.linspace(-350, 350, 29))
    work_area = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    assert MODEL.sees(work_area, margin_px=20).all()


def test_model_is_hashable_value() -> None:
    again = CameraModel.default()
    assert again == MODEL and hash(again) == hash(MODEL)
    assert np.allclose(MODEL.position_mm, (370.0, 20.0, 900.0))


# --- rasterising -------------------------------------------------------------------------


def test_polygon_coverage_is_area_exact() -> None:
    rng = np.random.default_rng(4)
    for _ in range(20):
        centre = rng.uniform(30, 50, 2)
        angles = np.sort(rng.uniform(0, 2 * np.pi, 7))
        radii = rng.uniform(8, 25, 7)
        polygon = centre + np.column_stack([radii * np.cos(angles), radii * np.sin(angles)])
        alpha = polygon_coverage([polygon], (80, 80)).astype(np.float64)
        area, centroid = polygon_area_centroid(polygon)
        assert alpha.sum() == pytest.approx(abs(area), abs=0.06)  # of ~600 px²
        rows, cols = np.mgrid[0:80, 0:80]
        got = np.array([(alpha * cols).sum(), (alpha * rows).sum()]) / alpha.sum()
        assert np.abs(got - centroid).max() < 2e-3


def test_workpiece_library_is_centred_on_area_centroids() -> None:
    for shape in WORKPIECE_SHAPES.values():
        area, centroid = polygon_area_centroid(np.asarray(shape.outline_mm))
        assert area > 0, shape.name  # counter-clockwise
        assert np.abs(centroid).max() < 1e-9, shape.name
    piece = Workpiece.named("l-bracket", 400.0, 50.0, 30.0)
    assert np.allclose(piece.centroid_table_mm(), (400.0, 50.0))
    with pytest.raises(ValueError, match="known shapes"):
        Workpiece.named("banana", 0, 0)


def test_a_table_printed_at_another_scale_moves_the_markers_not_their_size() -> None:
    layout = Scene().marker_positions_mm
    printed = Scene.printed(layout, 36.0, scale=1.02)
    centre = np.mean(layout, axis=0)
    np.testing.assert_allclose(
        np.asarray(printed.marker_positions_mm) - centre, 1.02 * (np.asarray(layout) - centre)
    )
    assert printed.marker_size_mm == 36.0
    assert Scene.printed(layout).marker_positions_mm == Scene().marker_positions_mm


def test_placing_a_workpiece_on_a_marker_warns(caplog: pytest.LogCaptureFixture) -> None:
    scene = Scene()
    with caplog.at_level(logging.WARNING):
        scene.place_workpiece("square-60", 400.0, 0.0)
    assert "covers marker 4" in caplog.text


# --- the table view ----------------------------------------------------------------------


def test_table_frame_is_reproducible_and_noisy() -> None:
    scene = Scene()
    first = render_table(scene, MODEL, np.random.default_rng(5))
    assert first.shape == (1080, 1920, 3) and first.dtype == np.uint8
    assert np.array_equal(first, render_table(scene, MODEL, np.random.default_rng(5)))
    other = render_table(scene, MODEL, np.random.default_rng(6))
    difference = first.astype(np.float64) - other
    # two independent noise draws: their difference has sigma √2 · noise_sigma
    assert difference.std() / np.sqrt(2) == pytest.approx(scene.noise_sigma, rel=0.15)


def test_all_nine_markers_are_found_at_their_true_centres() -> None:
    scene = Scene()
    frame = render_table(scene, MODEL, np.random.default_rng(7))
    parameters = cv2.aruco.DetectorParameters()
    parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(aruco_dictionary(), parameters)
    corners, ids, _ = detector.detectMarkers(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))
    assert ids is not None
    assert sorted(ids.ravel().tolist()) == list(range(9))
    truth = marker_centre_pixels(scene, MODEL)
    errors = {
        int(i): float(np.linalg.norm(diagonal_intersection(c.reshape(4, 2)) - truth[int(i)]))
        for c, i in zip(corners, ids.ravel(), strict=True)
    }
    assert max(errors.values()) < 0.3, errors


# --- chessboard views --------------------------------------------------------------------


@pytest.fixture(scope="module")
def chessboard_detections() -> list[tuple[np.ndarray, np.ndarray]]:
    """(detected, true) corner pixels for every default view."""
    rng = np.random.default_rng(8)
    found = []
    for pose in default_chessboard_poses(MODEL, DEFAULT_CHESSBOARD):
        frame = render_chessboard_view(MODEL, DEFAULT_CHESSBOARD, pose, rng=rng)
        grey = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        ok, corners = cv2.findChessboardCorners(grey, DEFAULT_CHESSBOARD.pattern_size)
        assert ok, "chessboard not found"
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
        corners = cv2.cornerSubPix(grey, corners, (7, 7), (-1, -1), criteria).reshape(-1, 2)
        truth = chessboard_corner_pixels(MODEL, DEFAULT_CHESSBOARD, pose)
        if np.linalg.norm(corners[0] - truth[0]) > np.linalg.norm(corners[0] - truth[-1]):
            corners = corners[::-1]  # OpenCV may number a symmetric board from the other end
        found.append((corners.astype(np.float64), truth))
    return found


def test_default_chessboard_poses_are_varied_and_in_view() -> None:
    poses = default_chessboard_poses(MODEL, DEFAULT_CHESSBOARD)
    assert len(poses) >= 10
    tilts = [np.degrees(np.arccos(pose.rotation[2, 2])) for pose in poses]
    assert min(tilts) >= 20 and max(tilts) <= 35
    for pose in poses:
        plate = MODEL.project_camera_frame(pose.to_camera(DEFAULT_CHESSBOARD.plate_corners_mm()))
        assert (plate >= 0).all() and (plate < (1920, 1080)).all()
    centres = np.array(
        [chessboard_corner_pixels(MODEL, DEFAULT_CHESSBOARD, p).mean(0) for p in poses]
    )
    assert np.ptp(centres[:, 0]) > 800 and np.ptp(centres[:, 1]) > 400


def test_chessboard_corners_are_found_at_their_true_pixels(
    chessboard_detections: list[tuple[np.ndarray, np.ndarray]],
) -> None:
    worst = max(
        np.linalg.norm(found - truth, axis=1).max() for found, truth in chessboard_detections
    )
    assert worst < 0.2


def test_calibration_from_the_default_views_recovers_the_intrinsics(
    chessboard_detections: list[tuple[np.ndarray, np.ndarray]],
) -> None:
    objects = [DEFAULT_CHESSBOARD.object_points()] * len(chessboard_detections)
    images = [found.astype(np.float32) for found, _ in chessboard_detections]
    rms, matrix, _, _, _ = cv2.calibrateCamera(objects, images, (1920, 1080), None, None)
    assert rms < 0.2
    assert matrix[0, 0] == pytest.approx(MODEL.fx, rel=0.02)
    assert matrix[1, 1] == pytest.approx(MODEL.fy, rel=0.02)
    assert matrix[0, 2] == pytest.approx(MODEL.cx, abs=3.0)
    assert matrix[1, 2] == pytest.approx(MODEL.cy, abs=3.0)


# --- workpieces --------------------------------------------------------------------------

PLACEMENTS = [
    ("rect-120x80", 325.0, 75.0, 15.0),
    ("l-bracket", 475.0, -75.0, -40.0),
    ("hexagon", 640.0, 0.0, 10.0),
    ("disc-70", 150.0, -75.0, 0.0),
    ("rounded-rect-100x60", 400.0, -240.0, 33.0),
    ("square-60", 475.0, 75.0, 60.0),
]


@pytest.fixture(scope="module")
def workpiece_frame() -> tuple[Scene, np.ndarray]:
    scene = Scene()
    for name, x, y, rotation in PLACEMENTS:
        scene.place_workpiece(name, x, y, rotation)
    return scene, render_table(scene, MODEL, np.random.default_rng(9))


def _outline_on_table(frame: np.ndarray, piece: Workpiece) -> np.ndarray:
    """The workpiece's contour (threshold + findContours) mapped onto the table, mm."""
    grey = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    _, binary = cv2.threshold(grey, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
    contours, _ = cv2.findContours(binary, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    u, v = MODEL.table_to_pixel(piece.centroid_table_mm())
    mine = [c for c in contours if cv2.pointPolygonTest(c, (float(u), float(v)), False) > 0]
    assert len(mine) == 1
    return MODEL.pixel_to_table(mine[0].reshape(-1, 2).astype(np.float64))


@pytest.mark.parametrize("index", range(len(PLACEMENTS)), ids=[p[0] for p in PLACEMENTS])
def test_workpiece_contour_maps_back_to_its_true_centroid(
    workpiece_frame: tuple[Scene, np.ndarray], index: int
) -> None:
    scene, frame = workpiece_frame
    piece = scene.workpieces[index]
    _, centroid = polygon_area_centroid(_outline_on_table(frame, piece))
    assert np.linalg.norm(centroid - piece.centroid_table_mm()) < 1.0


def test_rectangle_rotation_is_measurable(workpiece_frame: tuple[Scene, np.ndarray]) -> None:
    scene, frame = workpiece_frame
    piece = scene.workpieces[0]  # rect-120x80 at 15°
    (_, _), (w, h), angle = cv2.minAreaRect(_outline_on_table(frame, piece).astype(np.float32))
    long_axis = angle if w >= h else angle + 90.0
    error = (long_axis - piece.rotation_deg + 90.0) % 180.0 - 90.0
    assert abs(error) < 1.0
    outline_px = workpiece_outline_pixels(piece, MODEL)
    assert (
        outline_px.shape == (4, 2)
        and MODEL.sees(np.column_stack([piece.outline_table_mm(), np.zeros(4)])).all()
    )
