"""The simulated camera's degradations are really applied, each as specified, and only when set.

Frames are rendered without noise where a degradation is compared with the clean frame, so a
difference is the degradation's own. No accuracy thresholds: that is bench.vision_accuracy's
report; here only that the frame differs the way each figure says, and that the robot
calibration still succeeds under all of them at once.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from server.drivers.sim.camera_degradations import Degradations, light_field
from server.drivers.sim.camera_model import DEFAULT_CAMERA_MODEL
from server.drivers.sim.camera_scene import (
    Scene,
    marker_centre_pixels,
    marker_corners_mm,
    render_table,
)
from server.vision.homography import fit_plane_calibration
from server.vision.markers import MarkerDetector

SIZE = (DEFAULT_CAMERA_MODEL.width, DEFAULT_CAMERA_MODEL.height)


def frame(degradations: Degradations | None, noise: float = 0.0) -> np.ndarray:
    return render_table(Scene(noise_sigma=noise, degradations=degradations)).astype(np.float64)


@pytest.fixture(scope="module")
def clean() -> np.ndarray:
    return frame(None)


def test_off_by_default_and_neutral_when_empty(clean: np.ndarray) -> None:
    assert Scene().degradations is None
    np.testing.assert_array_equal(frame(Degradations()), clean)


def test_blur_lowers_the_sharpness_of_the_edges(clean: np.ndarray) -> None:
    blurred = frame(Degradations(blur_px=0.8))
    sharpness = [cv2.Laplacian(f[..., 1], cv2.CV_64F).var() for f in (clean, blurred)]
    assert sharpness[1] < 0.6 * sharpness[0]


def test_residual_distortion_moves_features_by_the_stated_amount() -> None:
    amount = 2.0  # px at the image corner: large enough to see per marker
    degradations = Degradations(residual_distortion_px=amount)
    grid = np.stack(np.meshgrid(np.arange(0, SIZE[0], 7.0), np.arange(0, SIZE[1], 7.0)), -1)
    moved = degradations.distort_pixels(grid.reshape(-1, 2), SIZE) - grid.reshape(-1, 2)
    assert np.abs(moved).max() == pytest.approx(amount, rel=1e-3)  # the stated amplitude
    truth = marker_centre_pixels(Scene())
    detector = MarkerDetector(fast=False)
    found = detector.detect(render_table(Scene(noise_sigma=0.0, degradations=degradations)))
    shifts = []
    for marker_id, (u, v) in truth.items():
        expected = degradations.distort_pixels([[u, v]], SIZE)[0]
        shifts.append(float(np.linalg.norm(expected - (u, v))))
        assert np.linalg.norm(found[marker_id].centre - expected) < 0.15, marker_id
    assert max(shifts) > 0.3  # the outer markers really moved, more than the check's slack


def test_uneven_light_scales_the_frame_by_its_field(clean: np.ndarray) -> None:
    field = light_field(0.3, *SIZE)
    assert 1.0 - field.min() / field.max() == pytest.approx(0.3, rel=1e-3)
    lit = frame(Degradations(uneven_light=0.3))
    unclipped = lit < 255
    expected = clean * field[..., None]
    # each frame is rounded to whole grey levels: at most half a level each, scaled by the gain
    assert np.abs(lit - expected)[unclipped].max() <= 0.5 + 0.5 * float(field.max()) + 1e-6
    assert np.abs(lit - clean).max() > 10  # and it is not a small effect


def test_noise_has_the_stated_sigma(clean: np.ndarray) -> None:
    noisy = frame(Degradations(noise_sigma=4.0), noise=2.0)
    mid = (clean > 30) & (clean < 220)  # no clipping at either end
    assert float((noisy - clean)[mid].std()) == pytest.approx(4.0, rel=0.05)


def test_jpeg_compression_is_applied() -> None:
    raw = render_table(Scene(noise_sigma=2.0))
    compressed = render_table(Scene(noise_sigma=2.0, degradations=Degradations(jpeg_quality=85)))
    _, encoded = cv2.imencode(".jpg", raw, [cv2.IMWRITE_JPEG_QUALITY, 85])
    np.testing.assert_array_equal(compressed, cv2.imdecode(encoded, cv2.IMREAD_UNCHANGED))
    assert np.abs(compressed.astype(int) - raw.astype(int)).mean() > 0.5


def test_print_scale_makes_the_sheets_larger_about_the_same_centres() -> None:
    scaled = Scene(degradations=Degradations(print_scale=1.005))
    for (i, sheet), plain in zip(
        marker_corners_mm(scaled).items(), marker_corners_mm(Scene()).values(), strict=True
    ):
        side = np.linalg.norm(sheet[1] - sheet[0])
        assert side == pytest.approx(30.0 * 1.005)
        np.testing.assert_allclose(sheet.mean(axis=0), plain.mean(axis=0))
        np.testing.assert_allclose(sheet.mean(axis=0), scaled.marker_positions_mm[i])
    assert not np.array_equal(render_table(scaled), render_table(Scene()))


def test_robot_calibration_still_succeeds_under_all_of_them() -> None:
    scene = Scene(degradations=Degradations.realistic())
    found = MarkerDetector(fast=False).detect(render_table(scene, rng=np.random.default_rng(5)))
    assert sorted(found) == list(range(9))
    calibration = fit_plane_calibration(
        {i: d.centre for i, d in found.items()}, dict(enumerate(scene.marker_positions_mm))
    )
    assert calibration.max_error_mm < 1.0  # a functional bound: the nine centres fit a plane
