"""Chessboard corners, intrinsic calibration and undistortion against the exact camera model."""

from __future__ import annotations

import json

import numpy as np
import pytest

from server.drivers.sim.camera_chessboard import (
    DEFAULT_CHESSBOARD,
    chessboard_corner_pixels,
    default_chessboard_poses,
    render_chessboard_view,
)
from server.drivers.sim.camera_model import DEFAULT_CAMERA_MODEL
from server.drivers.sim.camera_scene import Scene, marker_centre_pixels, render_table
from server.vision.homography import fit_plane_calibration, pixels_to_robot
from server.vision.intrinsics import (
    Intrinsics,
    Undistorter,
    calibrate_intrinsics,
    find_chessboard,
    intrinsics_of,
)
from server.vision.markers import MarkerDetector

MODEL = DEFAULT_CAMERA_MODEL
BOARD = DEFAULT_CHESSBOARD


@pytest.fixture(scope="module")
def views() -> list[tuple[np.ndarray, np.ndarray]]:
    """(frame, ground-truth corners) of every default board pose, with sensor noise."""
    return [
        (
            render_chessboard_view(MODEL, BOARD, pose, rng=np.random.default_rng(index)),
            chessboard_corner_pixels(MODEL, BOARD, pose),
        )
        for index, pose in enumerate(default_chessboard_poses(MODEL, BOARD))
    ]


@pytest.fixture(scope="module")
def corner_sets(views: list[tuple[np.ndarray, np.ndarray]]) -> list[np.ndarray]:
    found = [find_chessboard(frame, BOARD.pattern_size) for frame, _ in views]
    assert all(c is not None for c in found)
    return [c for c in found if c is not None]


@pytest.fixture(scope="module")
def calibrated(corner_sets: list[np.ndarray]) -> Intrinsics:
    return calibrate_intrinsics(corner_sets, BOARD.pattern_size, BOARD.square_mm, MODEL.size)


@pytest.fixture(scope="module")
def exact() -> Intrinsics:
    return intrinsics_of(MODEL.camera_matrix, MODEL.dist_coeffs, MODEL.size)


def test_chessboard_corners_are_sub_pixel_accurate(
    views: list[tuple[np.ndarray, np.ndarray]], corner_sets: list[np.ndarray]
) -> None:
    for (_, truth), corners in zip(views, corner_sets, strict=True):
        assert corners.shape == (BOARD.cols * BOARD.rows, 2)
        # OpenCV may report a symmetric board from either end; both orders are valid
        error = min(
            np.linalg.norm(corners - truth, axis=1).max(),
            np.linalg.norm(corners[::-1] - truth, axis=1).max(),
        )
        assert error < 0.25


def test_no_chessboard_on_the_table() -> None:
    assert find_chessboard(render_table(Scene()), BOARD.pattern_size) is None


def test_calibration_recovers_the_focal_length(calibrated: Intrinsics) -> None:
    assert calibrated.fx == pytest.approx(MODEL.fx, rel=0.02)
    assert calibrated.fy == pytest.approx(MODEL.fy, rel=0.02)
    assert calibrated.camera_matrix[0, 2] == pytest.approx(MODEL.cx, abs=10.0)
    assert calibrated.camera_matrix[1, 2] == pytest.approx(MODEL.cy, abs=10.0)
    assert calibrated.rms_px < 0.3
    assert calibrated.views == len(default_chessboard_poses(MODEL, BOARD))
    assert calibrated.image_size == (1920, 1080)


def test_calibrated_intrinsics_give_a_half_millimetre_table_calibration(
    calibrated: Intrinsics,
) -> None:
    """What matters downstream: the table calibration made through them is as good."""
    scene = Scene()
    undistorter = Undistorter(calibrated)
    frame = undistorter(render_table(scene, rng=np.random.default_rng(4)))
    detections = MarkerDetector(fast=False).detect(frame)
    robot_mm = dict(enumerate(scene.marker_positions_mm))
    calibration = fit_plane_calibration({i: d.centre for i, d in detections.items()}, robot_mm)
    assert calibration.max_error_mm < 0.5
    grid = np.stack(np.meshgrid(np.linspace(200, 600, 9), np.linspace(-250, 250, 11)), axis=-1)
    table = grid.reshape(-1, 2)
    pixels = undistorter.points(MODEL.table_to_pixel(table))
    errors = np.linalg.norm(pixels_to_robot(calibration.homography, pixels) - table, axis=1)
    assert errors.max() < 0.5


def test_fewer_than_five_views_is_refused(corner_sets: list[np.ndarray]) -> None:
    with pytest.raises(ValueError, match="at least 5 chessboard views"):
        calibrate_intrinsics(corner_sets[:4], BOARD.pattern_size, BOARD.square_mm, MODEL.size)


def test_a_view_with_the_wrong_corner_count_is_refused(corner_sets: list[np.ndarray]) -> None:
    broken = [*corner_sets[:5], corner_sets[5][:-1]]
    with pytest.raises(ValueError, match="view 5 has 53 corners"):
        calibrate_intrinsics(broken, BOARD.pattern_size, BOARD.square_mm, MODEL.size)


def test_intrinsics_round_trip_through_json(calibrated: Intrinsics) -> None:
    restored = Intrinsics.from_dict(json.loads(json.dumps(calibrated.to_dict())))
    np.testing.assert_array_equal(restored.camera_matrix, calibrated.camera_matrix)
    np.testing.assert_array_equal(restored.dist_coeffs, calibrated.dist_coeffs)
    assert restored.image_size == calibrated.image_size
    assert restored.rms_px == calibrated.rms_px and restored.views == calibrated.views


def test_undistorted_points_are_the_ideal_pinhole_projection(exact: Intrinsics) -> None:
    table = np.array([[100.0, -500.0], [400.0, 0.0], [700.0, 550.0], [250.0, 300.0]])
    raw = MODEL.table_to_pixel(table)
    rays = MODEL.to_camera_frame(np.hstack([table, np.zeros((len(table), 1))]))
    ideal = rays[:, :2] / rays[:, 2:] * [MODEL.fx, MODEL.fy] + [MODEL.cx, MODEL.cy]
    undistorter = Undistorter(exact)
    np.testing.assert_allclose(undistorter.points(raw), ideal, atol=1e-6)
    np.testing.assert_allclose(undistorter.distort_points(ideal), raw, atol=1e-6)


def test_undistorted_frame_and_undistorted_points_agree(exact: Intrinsics) -> None:
    """Measuring on an undistorted frame and undistorting raw measurements are equivalent."""
    frame = render_table(Scene(), rng=np.random.default_rng(2))
    undistorter = Undistorter(exact)
    detector = MarkerDetector(fast=False)
    on_frame = detector.detect(undistorter(frame))
    truth = marker_centre_pixels(Scene())
    for marker_id, detection in on_frame.items():
        expected = undistorter.points(np.array(truth[marker_id]))
        assert np.linalg.norm(detection.centre - expected) < 0.3


def test_a_frame_of_the_wrong_size_is_refused(exact: Intrinsics) -> None:
    with pytest.raises(ValueError, match="recalibrate"):
        Undistorter(exact)(np.zeros((720, 1280, 3), dtype=np.uint8))
