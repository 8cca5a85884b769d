"""Robot calibration and contour matching under realistic imaging, over the whole field.

The clean simulator's frames are exact; a real table's are not (see
server/drivers/sim/camera_degradations.py). For the clean frame, each degradation alone and
all of them together (`Degradations.realistic()`), this fits the lens model as the cell does
(the twelve default chessboard views, seen through the same lens: its residual distortion
included, which the five-term model can only partly absorb), renders the default table as
the cell's camera sees it, undistorts it with the fitted model, runs the robot calibration
the way the cell does (reference detector, homography from the nine marker centres to their
taught positions) and then measures:

- calibration: ground-truth table points on a 17×21 grid over the marker field (x 200..600,
  y -250..250 mm), each mapped from where it really appears in the frame through the
  calibration, against where it is; the markers' printed side through the map (the cell's
  scale check);
- contour match: six workpieces placed over the field (the library taught under the same
  camera at x 400, y 300, 0°): the part's true outline where it was taught, moved by the
  match's transform, against its true outline where it lies (distance of each vertex to it:
  where a taught spray path lands on the part), and the detected centroid's error.

No timing: accuracy only. A table and bench/results/vision_accuracy.json.
"""

from __future__ import annotations

import argparse
import functools
from typing import Any

import cv2
import numpy as np

from bench.report import emit
from server.drivers.sim.camera_chessboard import (
    DEFAULT_CHESSBOARD,
    default_chessboard_poses,
    render_chessboard_view,
)
from server.drivers.sim.camera_degradations import Degradations
from server.drivers.sim.camera_model import DEFAULT_CAMERA_MODEL
from server.drivers.sim.camera_scene import WORKPIECE_SHAPES, Scene, Workpiece, render_table
from server.vision.homography import fit_plane_calibration, mapped_side_mm, pixels_to_robot
from server.vision.intrinsics import Intrinsics, Undistorter, calibrate_intrinsics, find_chessboard
from server.vision.markers import MarkerDetector, border_corners
from server.vision.outlines import (
    find_outlines,
    match_outline,
    outline_pose,
    outline_to_mm,
    transform_outline,
)

MODEL = DEFAULT_CAMERA_MODEL
SIZE = (MODEL.width, MODEL.height)
EXCLUSION_SCALE = 1.8
TAUGHT_AT = (400.0, 300.0, 0.0)  # where each part is placed to teach the library (x, y mm, °)
REALISTIC = Degradations.realistic()
CONDITIONS: dict[str, Degradations | None] = {
    "clean": None,
    "residual distortion 0.5 px": Degradations(residual_distortion_px=0.5),
    "blur σ 0.8 px": Degradations(blur_px=0.8),
    "uneven light 30 %": Degradations(uneven_light=0.3),
    "noise σ 4": Degradations(noise_sigma=4.0),
    "JPEG q85": Degradations(jpeg_quality=85),
    "sheets printed +0.5 %": Degradations(print_scale=1.005),
    "all together": REALISTIC,
}
PLACEMENTS = [
    ("rect-120x80", 400.0, -300.0, 179.0),
    ("l-bracket", 250.0, 75.0, -135.0),
    ("hexagon", 150.0, -20.0, 10.0),
    ("disc-70", 650.0, 0.0, 0.0),
    ("square-60", 650.0, 300.0, 44.0),
    ("rounded-rect-100x60", 650.0, -300.0, 91.0),
]


def field_points() -> np.ndarray:
    grid = np.stack(np.meshgrid(np.linspace(200, 600, 17), np.linspace(-250, 250, 21)), axis=-1)
    return grid.reshape(-1, 2)


def seen_at(points_mm: np.ndarray, degradations: Degradations | None) -> np.ndarray:
    """Where table points really appear in the raw frame."""
    pixels = MODEL.table_to_pixel(points_mm)
    return pixels if degradations is None else degradations.distort_pixels(pixels, SIZE)


@functools.lru_cache(maxsize=4)
def fitted_intrinsics(residual_distortion_px: float) -> Intrinsics:
    """The lens model fitted on the default chessboard views seen through a lens with this
    residual distortion (the views' noise and light as the simulator's own)."""
    lens = Degradations(residual_distortion_px=residual_distortion_px)
    board = DEFAULT_CHESSBOARD
    corner_sets = []
    for index, pose in enumerate(default_chessboard_poses(MODEL, board)):
        view = render_chessboard_view(MODEL, board, pose, rng=np.random.default_rng(index))
        seen = lens.apply_to_light(view.astype(np.float32))
        corners = find_chessboard(
            np.clip(np.rint(seen), 0, 255).astype(np.uint8), board.pattern_size
        )
        if corners is None:
            raise RuntimeError(f"chessboard view {index} not found")
        corner_sets.append(corners)
    return calibrate_intrinsics(corner_sets, board.pattern_size, board.square_mm, MODEL.size)


def condition_row(
    name: str, degradations: Degradations | None, seeds: int, detector: MarkerDetector
) -> dict[str, Any]:
    residual = degradations.residual_distortion_px if degradations else 0.0
    undistorter = Undistorter(fitted_intrinsics(residual))
    table = field_points()
    field_errors, residuals, sides = [], [], []
    homography = None
    for seed in range(seeds):
        scene = Scene(degradations=degradations)
        frame = undistorter(render_table(scene, rng=np.random.default_rng(seed)))
        detections = detector.detect(frame)
        robot_mm = dict(enumerate(scene.marker_positions_mm))
        calibration = fit_plane_calibration({i: d.centre for i, d in detections.items()}, robot_mm)
        homography = homography if homography is not None else calibration.homography
        mapped = pixels_to_robot(
            calibration.homography, undistorter.points(seen_at(table, degradations))
        )
        field_errors.append(np.linalg.norm(mapped - table, axis=1))
        residuals.append(calibration.max_error_mm)
        for det in detections.values():
            edges = border_corners(frame, det.corners, detector.dictionary.markerSize + 2)
            sides.append(mapped_side_mm(calibration.homography, edges))
    errors = np.concatenate(field_errors)
    row: dict[str, Any] = {
        "condition": name,
        "calibration_field_mean_mm": round(float(errors.mean()), 4),
        "calibration_field_max_mm": round(float(errors.max()), 4),
        "marker_residual_max_mm": round(max(residuals), 4),
        "marker_side_error_pct": round(100 * (float(np.mean(sides)) / 30.0 - 1), 3),
    }
    assert homography is not None
    row.update(match_errors(degradations, undistorter, homography, detector))
    return row


def match_errors(
    degradations: Degradations | None,
    undistorter: Undistorter,
    homography: np.ndarray,
    detector: MarkerDetector,
) -> dict[str, float]:
    def outline_of(scene: Scene, seed: int) -> np.ndarray:
        image = undistorter(render_table(scene, rng=np.random.default_rng(seed)))
        found = detector.detect(image)
        exclude = [d.centre + (d.corners - d.centre) * EXCLUSION_SCALE for d in found.values()]
        return outline_to_mm(find_outlines(image, exclude=exclude)[0], homography)

    library = {}
    for shape in WORKPIECE_SHAPES:
        teach = Scene(degradations=degradations)
        teach.place_workpiece(shape, *TAUGHT_AT)
        library[shape] = outline_of(teach, 99)
    outline_errors, centre_errors = [], []
    for index, (shape, x, y, turn) in enumerate(PLACEMENTS):
        scene = Scene(degradations=degradations)
        scene.place_workpiece(shape, x, y, turn)
        outline = outline_of(scene, 200 + index)
        match = match_outline(outline, library)
        if match is None or match.workpiece_id != shape:
            raise RuntimeError(f"{shape} not matched under {degradations}")
        # where the part's true outline, as taught, lands through the match, against where it
        # is: the error of the pose over the part's extent (the detected outline's rounded
        # corners are the same when taught and when matched, so they cancel)
        taught = Workpiece.named(shape, *TAUGHT_AT).outline_table_mm()
        landed = transform_outline(taught, match.transform)
        truth = Workpiece.named(shape, x, y, turn).outline_table_mm().astype(np.float32)
        distances = [
            abs(cv2.pointPolygonTest(truth, (float(px), float(py)), True)) for px, py in landed
        ]
        outline_errors.extend(distances)
        pose = outline_pose(outline)
        centre_errors.append(float(np.hypot(pose.x - x, pose.y - y)))
    return {
        "match_outline_mean_mm": round(float(np.mean(outline_errors)), 4),
        "match_outline_max_mm": round(float(np.max(outline_errors)), 4),
        "match_centroid_max_mm": round(max(centre_errors), 4),
    }


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seeds", type=int, default=3, help="noise seeds per condition")
    parser.add_argument(
        "--only", action="append", choices=list(CONDITIONS), help="run only these conditions"
    )
    args = parser.parse_args(argv)
    detector = MarkerDetector(fast=False)  # the calibration's detector
    names = args.only or list(CONDITIONS)
    rows = [condition_row(name, CONDITIONS[name], args.seeds, detector) for name in names]
    emit("vision_accuracy", rows, {"seeds": args.seeds, "realistic": repr(REALISTIC)})
    return rows


if __name__ == "__main__":
    main()
