"""Marker detection against the simulator's exact ground truth.

The robot calibration is only as good as the marker centres, so the reference detector is
held to 0.3 px of where the simulator's camera model puts each centre, and the fast detector
(the one used while the cell runs) to 0.1 px of the reference, on noisy 1920×1080 frames.
"""

from __future__ import annotations

import numpy as np
import pytest

from server.drivers.sim.camera_scene import (
    Scene,
    marker_centre_pixels,
    marker_corner_pixels,
    render_table,
)
from server.vision.markers import (
    MarkerDetection,
    MarkerDetector,
    border_corners,
    diagonal_intersection,
    missing_markers,
)

ALL_MARKERS = list(range(9))


@pytest.fixture(scope="module")
def frames() -> list[np.ndarray]:
    """Noisy frames of the default table: same scene, fresh sensor noise each."""
    scene = Scene()
    return [render_table(scene, rng=np.random.default_rng(seed)) for seed in range(4)]


@pytest.fixture(scope="module")
def truth() -> dict[int, np.ndarray]:
    return {i: np.array(c) for i, c in marker_centre_pixels(Scene()).items()}


@pytest.fixture(scope="module")
def fast() -> MarkerDetector:
    return MarkerDetector(fast=True)


@pytest.fixture(scope="module")
def reference() -> MarkerDetector:
    return MarkerDetector(fast=False)


def test_both_detectors_find_all_nine_markers(
    frames: list[np.ndarray], fast: MarkerDetector, reference: MarkerDetector
) -> None:
    for frame in frames:
        assert sorted(fast.detect(frame)) == ALL_MARKERS
        assert sorted(reference.detect(frame)) == ALL_MARKERS


def test_reference_centres_match_ground_truth(
    frames: list[np.ndarray], reference: MarkerDetector, truth: dict[int, np.ndarray]
) -> None:
    for frame in frames:
        for marker_id, detection in reference.detect(frame).items():
            assert np.linalg.norm(detection.centre - truth[marker_id]) < 0.3, marker_id


def test_fast_centres_match_reference_within_a_tenth_of_a_pixel(
    frames: list[np.ndarray], fast: MarkerDetector, reference: MarkerDetector
) -> None:
    for frame in frames:
        quick, slow = fast.detect(frame), reference.detect(frame)
        for marker_id in ALL_MARKERS:
            gap = np.linalg.norm(quick[marker_id].centre - slow[marker_id].centre)
            assert gap < 0.1, (marker_id, gap)


def test_detection_shape_and_order(frames: list[np.ndarray], fast: MarkerDetector) -> None:
    detection = fast.detect(frames[0])[4]
    assert isinstance(detection, MarkerDetection)
    assert detection.marker_id == 4
    assert detection.corners.shape == (4, 2) and detection.corners.dtype == np.float64
    assert detection.centre.shape == (2,)
    # OpenCV order: top-left, top-right, bottom-right, bottom-left (clockwise in the image)
    c = detection.corners
    signed = np.sum(c[:, 0] * np.roll(c[:, 1], -1) - np.roll(c[:, 0], -1) * c[:, 1])
    assert signed > 0  # clockwise on screen is positive with y pointing down


def test_grey_input_gives_the_same_result(frames: list[np.ndarray], fast: MarkerDetector) -> None:
    import cv2

    grey = cv2.cvtColor(frames[0], cv2.COLOR_BGR2GRAY)
    a, b = fast.detect(frames[0]), fast.detect(grey)
    assert sorted(a) == sorted(b)
    for i in a:
        np.testing.assert_allclose(a[i].centre, b[i].centre, atol=1e-9)


def test_a_covered_marker_is_reported_missing() -> None:
    scene = Scene()
    scene.place_workpiece("rect-120x80", 400.0, 0.0)  # lies right over marker 4
    found = MarkerDetector().detect(render_table(scene))
    assert missing_markers(found) == [4]


def test_fast_mode_looks_again_at_full_resolution_for_expected_markers(
    frames: list[np.ndarray],
) -> None:
    detector = MarkerDetector(fast=True)
    real_find = detector._find

    def half_resolution_misses_marker_7(gray: np.ndarray) -> dict[int, np.ndarray]:
        found = real_find(gray)
        if gray.shape[0] < 1080:
            found.pop(7, None)
        return found

    real_quick = detector._find_quick

    def quick_pass_misses_marker_7(small: np.ndarray) -> dict[int, np.ndarray]:
        found = real_quick(small)
        found.pop(7, None)
        return found

    detector._find = half_resolution_misses_marker_7  # type: ignore[method-assign]
    detector._find_quick = quick_pass_misses_marker_7  # type: ignore[method-assign]
    assert 7 not in detector.detect(frames[0])
    assert 7 in detector.detect(frames[0], expected=ALL_MARKERS)


def test_no_markers_on_a_blank_frame(fast: MarkerDetector, reference: MarkerDetector) -> None:
    blank = np.full((1080, 1920, 3), 70, dtype=np.uint8)
    assert fast.detect(blank) == {}
    assert reference.detect(blank) == {}


def test_missing_markers() -> None:
    assert missing_markers([0, 1, 2, 3, 5, 6, 7, 8]) == [4]
    assert missing_markers({8: None, 0: None}, required=[0, 8, 9]) == [9]
    assert missing_markers([]) == ALL_MARKERS
    assert missing_markers(range(12)) == []


def test_diagonal_intersection_is_the_perspective_centre() -> None:
    # a trapezoid: the diagonals cross off the mean of the corners
    quad = np.array([[0.0, 0.0], [4.0, 0.0], [3.0, 2.0], [1.0, 2.0]])
    centre = diagonal_intersection(quad)
    np.testing.assert_allclose(centre, [2.0, 4.0 / 3.0])


def test_border_corners_find_the_printed_square_where_the_refined_corners_fall_inside(
    frames: list[np.ndarray], reference: MarkerDetector
) -> None:
    truth = marker_corner_pixels(Scene())
    for frame in frames[:2]:
        for marker_id, detection in reference.detect(frame).items():
            edges = border_corners(frame, detection.corners)
            edge_error = np.linalg.norm(edges - truth[marker_id], axis=1)
            corner_error = np.linalg.norm(detection.corners - truth[marker_id], axis=1)
            assert edge_error.mean() < 0.05, (marker_id, edge_error)
            assert corner_error.mean() > 2 * edge_error.mean(), (marker_id, corner_error)


def test_border_corners_without_a_border_is_a_clear_error() -> None:
    flat = np.full((200, 200), 128, dtype=np.uint8)
    square = np.array([[80.0, 80.0], [120.0, 80.0], [120.0, 120.0], [80.0, 120.0]])
    with pytest.raises(ValueError, match=r"edge 0 of the marker at \(100\.0, 100\.0\) px"):
        border_corners(flat, square)
