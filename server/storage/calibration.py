"""The cell's calibrations on disk: camera intrinsics and the image → robot-plane map.

Both are written atomically when an operation succeeds and read back at start,
so a restart keeps the last good calibration. The annotated image of the last
robot calibration is kept beside it for the HMI (GET /calibration/image).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from server.storage.files import read_json, write_bytes_atomic, write_json_atomic
from server.vision.homography import PlaneCalibration
from server.vision.intrinsics import Intrinsics, Undistorter

log = logging.getLogger(__name__)


class CalibrationStore:
    """Loads and saves the calibrations under `<data>/calibration/`."""

    def __init__(self, data_path: Path) -> None:
        self.directory = data_path / "calibration"
        self.robot: PlaneCalibration | None = None
        self.robot_meta: dict[str, Any] = {}
        self.camera: Intrinsics | None = None
        self.camera_meta: dict[str, Any] = {}
        self._undistorter: Undistorter | None = None
        self._load()

    @property
    def robot_path(self) -> Path:
        return self.directory / "robot.json"

    @property
    def camera_path(self) -> Path:
        return self.directory / "camera.json"

    @property
    def robot_image_path(self) -> Path:
        return self.directory / "robot.png"

    def _load(self) -> None:
        for path, loader in (
            (self.robot_path, self._load_robot),
            (self.camera_path, self._load_camera),
        ):
            try:
                document = read_json(path)
                if document is not None:
                    loader(document)
            except (ValueError, KeyError, TypeError) as exc:
                aside = path.with_suffix(f".corrupt-{int(time.time())}")
                path.replace(aside)
                log.error(
                    "calibration file %s unreadable (%s); kept as %s, recalibrate", path, exc, aside
                )

    def _load_robot(self, document: dict[str, Any]) -> None:
        self.robot = PlaneCalibration.from_dict(document["calibration"])
        self.robot_meta = {k: v for k, v in document.items() if k != "calibration"}

    def _load_camera(self, document: dict[str, Any]) -> None:
        self.camera = Intrinsics.from_dict(document["intrinsics"])
        self.camera_meta = {k: v for k, v in document.items() if k != "intrinsics"}
        self._undistorter = None

    def save_robot(
        self, calibration: PlaneCalibration, image_png: bytes | None, meta: dict[str, Any]
    ) -> None:
        if image_png is not None:
            write_bytes_atomic(self.robot_image_path, image_png)
        meta = {"created_at": time.time(), **meta}
        write_json_atomic(self.robot_path, {**meta, "calibration": calibration.to_dict()})
        self.robot, self.robot_meta = calibration, meta

    def save_camera(self, intrinsics: Intrinsics, meta: dict[str, Any]) -> None:
        meta = {"created_at": time.time(), **meta}
        write_json_atomic(self.camera_path, {**meta, "intrinsics": intrinsics.to_dict()})
        self.camera, self.camera_meta = intrinsics, meta
        self._undistorter = None  # the new calibration's maps, built when first asked for

    def undistort(self, frame: np.ndarray) -> np.ndarray:
        """The frame without lens distortion, when the camera is calibrated; else as it is.

        The remap tables (about 12 MB for 1920×1080) are built on the first call after a
        calibration is loaded or saved, not before: in this process only the camera's
        set-up view asks for them (a run's frames are undistorted in the image process),
        and a cell whose set-up view is never opened does not hold them."""
        camera, undistorter = self.camera, self._undistorter
        if camera is None:
            return frame
        if undistorter is None or undistorter.intrinsics is not camera:
            undistorter = self._undistorter = Undistorter(camera)
        return undistorter(frame)

    def summary(self) -> dict[str, Any]:
        """What GET /calibration shows."""
        robot = None
        if self.robot is not None:
            robot = {
                **self.robot_meta,
                "mean_error_mm": self.robot.mean_error_mm,
                "max_error_mm": self.robot.max_error_mm,
                "residuals_mm": {str(k): v for k, v in self.robot.residuals_mm.items()},
                "homography": np.asarray(self.robot.homography).tolist(),
                "has_image": self.robot_image_path.exists(),
            }
        camera = None
        if self.camera is not None:
            camera = {
                **self.camera_meta,
                "camera_matrix": np.asarray(self.camera.camera_matrix).tolist(),
                "dist_coeffs": np.asarray(self.camera.dist_coeffs).ravel().tolist(),
                "image_size": list(self.camera.image_size),
                "reprojection_error_px": self.camera.rms_px,
                "views": self.camera.views,
            }
        return {"robot": robot, "camera": camera}
