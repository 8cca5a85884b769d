"""The calibration store holds the camera's undistortion maps only once they are used.

The maps are about 12 MB at 1920×1080. In the server's process only the camera's
set-up view undistorts (a run's frames are undistorted in the image process), so a
store that built them at every load held them for nothing in a cell whose set-up view
is never opened.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from server.drivers.sim.camera_model import DEFAULT_CAMERA_MODEL
from server.storage.calibration import CalibrationStore
from server.vision.intrinsics import Undistorter, intrinsics_of

MODEL = DEFAULT_CAMERA_MODEL
INTRINSICS = intrinsics_of(MODEL.camera_matrix, MODEL.dist_coeffs, (MODEL.width, MODEL.height))


def frame() -> np.ndarray:
    rng = np.random.default_rng(7)
    return rng.integers(0, 255, (MODEL.height, MODEL.width, 3), dtype=np.uint8)


def test_a_loaded_or_saved_camera_calibration_builds_no_maps_until_a_frame_is_undistorted(
    tmp_path: Path,
) -> None:
    CalibrationStore(tmp_path).save_camera(INTRINSICS, {"views": 12})
    store = CalibrationStore(tmp_path)  # loaded at start, as the server does
    assert store.camera is not None
    assert store._undistorter is None
    store.save_camera(INTRINSICS, {"views": 12})  # a calibration made while running
    assert store._undistorter is None


def test_undistorting_through_the_store_is_the_calibrations_undistortion(tmp_path: Path) -> None:
    store = CalibrationStore(tmp_path)
    raw = frame()
    assert store.undistort(raw) is raw  # not calibrated: the frame as it is
    store.save_camera(INTRINSICS, {})
    expected = Undistorter(INTRINSICS)(raw)
    assert np.array_equal(store.undistort(raw), expected)
    maps = store._undistorter
    assert np.array_equal(store.undistort(raw), expected)
    assert store._undistorter is maps  # built once per calibration


def test_a_new_calibration_replaces_the_maps_of_the_one_before(tmp_path: Path) -> None:
    store = CalibrationStore(tmp_path)
    store.save_camera(INTRINSICS, {})
    store.undistort(frame())
    other = intrinsics_of(
        MODEL.camera_matrix, np.zeros(5), (MODEL.width, MODEL.height)
    )  # no distortion: the identity
    store.save_camera(other, {})
    raw = frame()
    assert np.array_equal(store.undistort(raw), Undistorter(other)(raw))
