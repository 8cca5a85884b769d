"""The image → table calibration against the simulator's exact camera.

The default simulated camera has lens distortion, so the homography is fitted on an
undistorted frame (with the model's exact intrinsics here; test_vision_intrinsics shows a
chessboard calibration recovers them). Claim under test: every marker centre maps to its robot
position within 0.5 mm.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from server.drivers.sim.camera_model import DEFAULT_CAMERA_MODEL
from server.drivers.sim.camera_scene import Scene, marker_centre_pixels, render_table
from server.vision.homography import (
    PlaneCalibration,
    annotate_markers,
    fit_plane_calibration,
    leave_one_out_errors,
    mapped_side_mm,
    pixels_to_robot,
    robot_to_pixels,
)
from server.vision.intrinsics import Undistorter, intrinsics_of
from server.vision.markers import MarkerDetector, border_corners

MODEL = DEFAULT_CAMERA_MODEL
ROBOT_MM = dict(enumerate(Scene().marker_positions_mm))


@pytest.fixture(scope="module")
def undistorter() -> Undistorter:
    return Undistorter(intrinsics_of(MODEL.camera_matrix, MODEL.dist_coeffs, MODEL.size))


@pytest.fixture(scope="module")
def raw_frame() -> np.ndarray:
    return render_table(Scene(), rng=np.random.default_rng(11))


@pytest.fixture(scope="module")
def calibration(raw_frame: np.ndarray, undistorter: Undistorter) -> PlaneCalibration:
    detections = MarkerDetector(fast=False).detect(undistorter(raw_frame))
    return fit_plane_calibration({i: d.centre for i, d in detections.items()}, ROBOT_MM)


def test_marker_centres_map_to_their_robot_positions(calibration: PlaneCalibration) -> None:
    assert sorted(calibration.residuals_mm) == list(range(9))
    assert calibration.max_error_mm < 0.5
    assert max(calibration.residuals_mm.values()) == pytest.approx(calibration.max_error_mm)
    assert calibration.mean_error_mm <= calibration.max_error_mm


def test_ground_truth_centres_map_within_half_a_millimetre(
    calibration: PlaneCalibration, undistorter: Undistorter
) -> None:
    truth = marker_centre_pixels(Scene())
    pixels = undistorter.points(np.array([truth[i] for i in range(9)]))
    mapped = pixels_to_robot(calibration.homography, pixels)
    errors = np.linalg.norm(mapped - np.array([ROBOT_MM[i] for i in range(9)]), axis=1)
    assert errors.max() < 0.5


def test_the_whole_marker_field_maps_within_half_a_millimetre(
    calibration: PlaneCalibration, undistorter: Undistorter
) -> None:
    """Not just at the markers: any table point between them (where parts lie)."""
    grid = np.stack(np.meshgrid(np.linspace(200, 600, 9), np.linspace(-250, 250, 11)), axis=-1)
    table = grid.reshape(-1, 2)
    pixels = undistorter.points(MODEL.table_to_pixel(table))
    errors = np.linalg.norm(pixels_to_robot(calibration.homography, pixels) - table, axis=1)
    assert errors.max() < 0.5


def test_detecting_on_the_raw_frame_and_undistorting_points_agrees(
    raw_frame: np.ndarray, undistorter: Undistorter
) -> None:
    detections = MarkerDetector(fast=False).detect(raw_frame)
    pixels = {i: undistorter.points(d.centre) for i, d in detections.items()}
    calibration = fit_plane_calibration(pixels, ROBOT_MM)
    assert calibration.max_error_mm < 0.5


def test_robot_to_pixels_inverts_pixels_to_robot(calibration: PlaneCalibration) -> None:
    points = np.array([[250.0, -150.0], [400.0, 0.0], [610.5, 200.25]])
    back = pixels_to_robot(calibration.homography, robot_to_pixels(calibration.homography, points))
    np.testing.assert_allclose(back, points, atol=1e-9)
    single = pixels_to_robot(calibration.homography, np.array([960.0, 540.0]))
    assert single.shape == (1, 2)


def test_a_bumped_marker_stands_out_in_the_residuals(raw_frame: np.ndarray) -> None:
    detections = MarkerDetector(fast=False).detect(raw_frame)
    bumped = dict(ROBOT_MM)
    bumped[3] = (bumped[3][0] + 4.0, bumped[3][1])
    calibration = fit_plane_calibration({i: d.centre for i, d in detections.items()}, bumped)
    worst = max(calibration.residuals_mm, key=calibration.residuals_mm.__getitem__)
    assert worst == 3
    assert calibration.max_error_mm > 1.0


def test_too_few_markers_is_a_clear_error() -> None:
    pixels = {0: np.array([10.0, 10.0]), 1: np.array([20.0, 10.0]), 2: np.array([20.0, 30.0])}
    with pytest.raises(ValueError, match="at least 4 markers"):
        fit_plane_calibration(pixels, ROBOT_MM)


def test_calibration_round_trips_through_json(calibration: PlaneCalibration) -> None:
    text = json.dumps(calibration.to_dict())
    restored = PlaneCalibration.from_dict(json.loads(text))
    np.testing.assert_array_equal(restored.homography, calibration.homography)
    assert restored.residuals_mm == calibration.residuals_mm
    assert restored.max_error_mm == calibration.max_error_mm
    assert restored.mean_error_mm == calibration.mean_error_mm


def test_annotation_is_a_marked_up_copy(
    raw_frame: np.ndarray, calibration: PlaneCalibration
) -> None:
    detections = MarkerDetector().detect(raw_frame)
    before = raw_frame.copy()
    annotated = annotate_markers(raw_frame, detections, calibration.residuals_mm)
    np.testing.assert_array_equal(raw_frame, before)  # the input is untouched
    assert annotated.shape == raw_frame.shape and annotated.dtype == np.uint8
    assert np.count_nonzero(np.any(annotated != raw_frame, axis=2)) > 1000
    grey = annotate_markers(raw_frame[..., 1], detections)
    assert grey.shape == raw_frame.shape


def _sides_through_the_map(scene: Scene, undistorter: Undistorter) -> tuple[list[float], float]:
    """Each marker's side (mm) through a map fitted to the configured (default) layout."""
    frame = undistorter(render_table(scene, rng=np.random.default_rng(5)))
    detections = MarkerDetector(fast=False).detect(frame)
    fit = fit_plane_calibration({i: d.centre for i, d in detections.items()}, ROBOT_MM)
    edges = [border_corners(frame, d.corners) for d in detections.values()]
    return [mapped_side_mm(fit.homography, corners) for corners in edges], fit.mean_error_mm


def test_the_printed_marker_side_comes_back_through_the_map(undistorter: Undistorter) -> None:
    sides, _ = _sides_through_the_map(Scene(), undistorter)
    assert len(sides) == 9
    for side in sides:
        assert side == pytest.approx(30.0, rel=0.001)  # a tenth of the 1 % the check allows


def test_the_detectors_own_corners_would_shrink_the_marker(
    raw_frame: np.ndarray, undistorter: Undistorter, calibration: PlaneCalibration
) -> None:
    """Why border_corners exists: sub-pixel L-corners sit inside the square."""
    frame = undistorter(raw_frame)
    detections = MarkerDetector(fast=False).detect(frame)
    homography = calibration.homography
    from_corners = np.mean([mapped_side_mm(homography, d.corners) for d in detections.values()])
    edges = [border_corners(frame, d.corners) for d in detections.values()]
    from_edges = np.mean([mapped_side_mm(homography, corners) for corners in edges])
    assert abs(from_edges - 30.0) < abs(from_corners - 30.0) / 5


@pytest.mark.parametrize("scale", [1.02, 0.98])
def test_a_layout_printed_at_another_scale_fits_itself_but_not_the_marker_side(
    scale: float, undistorter: Undistorter
) -> None:
    printed = Scene.printed(Scene().marker_positions_mm, 30.0, scale=scale)
    sides, mean_error = _sides_through_the_map(printed, undistorter)
    assert mean_error < 0.1  # the fit alone cannot tell
    assert np.mean(sides) == pytest.approx(30.0 / scale, rel=0.001)


def test_the_holdout_of_a_good_layout_is_small(raw_frame: np.ndarray) -> None:
    detections = MarkerDetector(fast=False).detect(raw_frame)
    errors = leave_one_out_errors({i: d.centre for i, d in detections.items()}, ROBOT_MM)
    assert sorted(errors) == list(range(9))
    assert max(errors.values()) < 0.5  # raw frame: lens distortion left in


def test_a_wrong_marker_position_hides_in_the_fit_but_not_in_the_holdout(
    raw_frame: np.ndarray, undistorter: Undistorter
) -> None:
    detections = MarkerDetector(fast=False).detect(undistorter(raw_frame))
    pixels = {i: d.centre for i, d in detections.items()}
    bumped = dict(ROBOT_MM)
    bumped[4] = (bumped[4][0] + 2.0, bumped[4][1])
    fit = fit_plane_calibration(pixels, bumped)
    assert fit.mean_error_mm < 0.5  # under half the default 1 mm limit: not even a warning
    errors = leave_one_out_errors(pixels, bumped)
    assert errors[4] == pytest.approx(2.0, abs=0.1)
    assert max(e for i, e in errors.items() if i != 4) < 1.0


def test_a_holdout_that_leaves_too_few_markers_is_a_clear_error() -> None:
    pixels = {i: np.array([10.0 * i, 5.0 * (i % 2)]) for i in range(4)}
    with pytest.raises(ValueError, match="at least 4 markers"):
        leave_one_out_errors(pixels, ROBOT_MM)
