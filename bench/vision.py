"""Vision on simulated 1920×1080 frames: detection speed, calibration accuracy, workpiece cost.

1. ArUco detection per frame (fresh sensor noise each frame, the default table's 45 px
   markers and 150 px ones): OpenCV's default detector, the reference (full resolution +
   sub-pixel corners), OpenCV's three threshold windows at half resolution and the fast path, run
   interleaved on the same frames; markers found, the largest centre gap to the reference
   and the largest centre and corner errors against the simulator's ground truth.
2. Calibration: intrinsics from the twelve default chessboard views (focal-length error),
   and the table calibration (marker residuals, and ground-truth table points over the marker
   field mapped through it) with exact and with calibrated intrinsics.
3. Per workpiece: undistortion, marker exclusion, contour finding, mm conversion, library
   matching (all six simulator shapes, taught by detecting each once at 0°) and spray-path
   planning (2 mm inward bead + 5 mm zigzag fill) on the matched library outline, with the
   centroid and turn errors against the simulator's pose.

Timing only the vision calls: frames are rendered outside the timed region. Three tables
and JSON files: bench/results/vision_detection.json, vision_calibration.json and
vision_workpieces.json.
"""

from __future__ import annotations

import argparse
import math
import time
from typing import Any

import cv2
import numpy as np

from bench.report import emit, percentiles_ms
from server.drivers.sim.camera_chessboard import (
    DEFAULT_CHESSBOARD,
    chessboard_corner_pixels,
    default_chessboard_poses,
    render_chessboard_view,
)
from server.drivers.sim.camera_model import DEFAULT_CAMERA_MODEL
from server.drivers.sim.camera_scene import (
    WORKPIECE_SHAPES,
    Scene,
    aruco_dictionary,
    marker_centre_pixels,
    marker_corner_pixels,
    render_table,
)
from server.vision.homography import fit_plane_calibration, pixels_to_robot
from server.vision.intrinsics import (
    Intrinsics,
    Undistorter,
    calibrate_intrinsics,
    find_chessboard,
    intrinsics_of,
)
from server.vision.markers import MarkerDetector, to_gray
from server.vision.outlines import (
    find_outlines,
    match_outline,
    outline_pose,
    outline_to_mm,
    transform_outline,
)
from server.vision.paths import SprayPattern, spray_polylines

MODEL = DEFAULT_CAMERA_MODEL
BOARD = DEFAULT_CHESSBOARD
EXCLUSION_SCALE = 1.8


def timed(call: Any, *args: Any, **kwargs: Any) -> tuple[Any, float]:
    started = time.perf_counter()
    result = call(*args, **kwargs)
    return result, time.perf_counter() - started


# Marker sizes on the image: the default table's 30 mm markers (~45 px) and 100 mm ones (~150 px).
MARKER_SIZES_MM = {45: 30.0, 150: 100.0}


def marker_scene(marker_px: int) -> Scene:
    """The default layout with markers of about `marker_px` on the image.

    The white margin is one cell of the marker (at least the default 7.5 mm): with the
    default margin of 7.5 mm, under half a cell of a 100 mm marker, the sheet's own outline
    decodes as the marker too and, being larger, is the one kept (centre right, corners 16 px
    out); a printed marker keeps at least a cell of white around it.
    """
    size = MARKER_SIZES_MM[marker_px]
    return Scene(marker_size_mm=size, quiet_zone_mm=max(7.5, size / 6.0))


def three_window_baseline(detector: MarkerDetector, frame: np.ndarray) -> dict[int, Any]:
    """The baseline the fast path is measured against: OpenCV's three threshold windows at
    half resolution, with the same full-resolution refinement."""
    gray = to_gray(frame)
    height, width = gray.shape
    small = cv2.resize(gray, (width // 2, height // 2), interpolation=cv2.INTER_AREA)
    coarse = {i: 2.0 * c + 0.5 for i, c in detector._find(small).items()}
    return {i: detector._refine(gray, i, c) for i, c in sorted(coarse.items())}


def detection_rows(frames: int, marker_px: int = 45) -> list[dict[str, Any]]:
    scene = marker_scene(marker_px)
    truth = marker_centre_pixels(scene)
    truth_corners = marker_corner_pixels(scene)
    opencv = cv2.aruco.ArucoDetector(aruco_dictionary(), cv2.aruco.DetectorParameters())
    reference, fast = MarkerDetector(fast=False), MarkerDetector(fast=True)
    before = MarkerDetector(fast=True)
    keys = ("default", "reference", "before", "fast")
    samples: dict[str, list[float]] = {k: [] for k in keys}
    found: dict[str, list[int]] = {k: [] for k in keys}
    gap_px = dict.fromkeys(keys, 0.0)
    centre_px = dict.fromkeys(keys, 0.0)
    corner_px = dict.fromkeys(keys, 0.0)
    rng = np.random.default_rng(1)
    render_table(scene, rng=rng)  # warm the simulator's caches
    for index in range(frames + 3):
        frame = render_table(scene, rng=rng)
        (_corners, ids, _), t_default = timed(opencv.detectMarkers, frame)
        results: dict[str, dict[int, Any]] = {}
        # interleaved, the order turned every frame so no path always runs on a warm cache
        calls = [
            ("reference", reference.detect),
            ("before", lambda f: three_window_baseline(before, f)),
            ("fast", fast.detect),
        ]
        timings = {"default": t_default}
        for key, call in calls[index % 3 :] + calls[: index % 3]:
            results[key], timings[key] = timed(call, frame)
        if index < 3:
            continue  # warm-up
        found["default"].append(0 if ids is None else len(ids))
        for key in keys:
            samples[key].append(timings[key])
        for key in ("reference", "before", "fast"):
            found[key].append(len(results[key]))
            for marker_id, det in results[key].items():
                slow = results["reference"].get(marker_id)
                if slow is not None:
                    gap_px[key] = max(gap_px[key], float(np.linalg.norm(det.centre - slow.centre)))
                centre_px[key] = max(
                    centre_px[key], float(np.linalg.norm(det.centre - truth[marker_id]))
                )
                corner_px[key] = max(
                    corner_px[key],
                    float(np.linalg.norm(det.corners - truth_corners[marker_id], axis=1).max()),
                )
    names = {
        "default": "OpenCV default detectMarkers (no refinement)",
        "reference": "reference (full res + sub-pixel)",
        "before": "three windows (half res, the baseline)",
        "fast": "fast (1 window, half or quarter res, fallbacks)",
    }
    rows = []
    for key, name in names.items():
        row: dict[str, Any] = {
            "measure": f"ArUco {marker_px} px: {name}",
            **percentiles_ms(samples[key]),
        }
        row["markers_found_min"] = min(found[key])
        if key != "default":
            row["max_centre_error_vs_truth_px"] = round(centre_px[key], 4)
            row["max_corner_error_vs_truth_px"] = round(corner_px[key], 4)
        if key in ("before", "fast"):
            row["max_centre_gap_vs_reference_px"] = round(gap_px[key], 4)
        rows.append(row)
    return rows


def table_errors(intrinsics: Intrinsics) -> dict[str, float]:
    scene = Scene()
    undistorter = Undistorter(intrinsics)
    frame = undistorter(render_table(scene, rng=np.random.default_rng(7)))
    detections = MarkerDetector(fast=False).detect(frame)
    robot_mm = dict(enumerate(scene.marker_positions_mm))
    calibration = fit_plane_calibration({i: d.centre for i, d in detections.items()}, robot_mm)
    grid = np.stack(np.meshgrid(np.linspace(200, 600, 17), np.linspace(-250, 250, 21)), axis=-1)
    table = grid.reshape(-1, 2)
    mapped = pixels_to_robot(
        calibration.homography, undistorter.points(MODEL.table_to_pixel(table))
    )
    errors = np.linalg.norm(mapped - table, axis=1)
    return {
        "marker_residual_mean_mm": round(calibration.mean_error_mm, 4),
        "marker_residual_max_mm": round(calibration.max_error_mm, 4),
        "field_error_mean_mm": round(float(errors.mean()), 4),
        "field_error_max_mm": round(float(errors.max()), 4),
    }


def calibration_rows() -> list[dict[str, Any]]:
    corner_sets, times, corner_errors = [], [], []
    for index, pose in enumerate(default_chessboard_poses(MODEL, BOARD)):
        frame = render_chessboard_view(MODEL, BOARD, pose, rng=np.random.default_rng(index))
        corners, seconds = timed(find_chessboard, frame, BOARD.pattern_size)
        assert corners is not None, f"chessboard view {index} not found"
        truth = chessboard_corner_pixels(MODEL, BOARD, pose)
        corner_errors.append(float(np.linalg.norm(corners - truth, axis=1).max()))
        corner_sets.append(corners)
        times.append(seconds)
    intrinsics, seconds = timed(
        calibrate_intrinsics, corner_sets, BOARD.pattern_size, BOARD.square_mm, MODEL.size
    )
    rows: list[dict[str, Any]] = [
        {
            "measure": "find_chessboard (1920×1080, 9×6)",
            **percentiles_ms(times),
            "max_corner_error_px": round(max(corner_errors), 4),
        },
        {
            "measure": f"calibrate_intrinsics ({len(corner_sets)} views)",
            **percentiles_ms([seconds]),
            "fx_error_pct": round(100 * (intrinsics.fx / MODEL.fx - 1), 4),
            "fy_error_pct": round(100 * (intrinsics.fy / MODEL.fy - 1), 4),
            "rms_px": round(intrinsics.rms_px, 4),
        },
    ]
    exact = intrinsics_of(MODEL.camera_matrix, MODEL.dist_coeffs, MODEL.size)
    for label, source in (("exact", exact), ("chessboard-calibrated", intrinsics)):
        rows.append({"measure": f"table calibration, {label} intrinsics", **table_errors(source)})
    return rows


def workpiece_rows(repeats: int) -> list[dict[str, Any]]:
    undistorter = Undistorter(intrinsics_of(MODEL.camera_matrix, MODEL.dist_coeffs, MODEL.size))
    base = Scene()
    frame = undistorter(render_table(base, rng=np.random.default_rng(3)))
    detections = MarkerDetector(fast=False).detect(frame)
    robot_mm = dict(enumerate(base.marker_positions_mm))
    homography = fit_plane_calibration(
        {i: d.centre for i, d in detections.items()}, robot_mm
    ).homography
    detector = MarkerDetector(fast=True)

    def outline_of(scene: Scene, seed: int) -> np.ndarray:
        image = undistorter(render_table(scene, rng=np.random.default_rng(seed)))
        found = detector.detect(image)
        exclude = [d.centre + (d.corners - d.centre) * EXCLUSION_SCALE for d in found.values()]
        return outline_to_mm(find_outlines(image, exclude=exclude)[0], homography)

    # the library as the cell builds it: each part detected once where it was taught (0°)
    library = {}
    for name in WORKPIECE_SHAPES:
        teach = Scene()
        teach.place_workpiece(name, 400.0, 300.0, 0.0)
        library[name] = outline_of(teach, 99)
    pattern = SprayPattern(outline_offset_mm=-2.0, fill="zigzag", fill_spacing_mm=5.0)
    placements = [
        ("rect-120x80", 400.0, -300.0, 179.0),
        ("l-bracket", 400.0, 300.0, -135.0),
        ("hexagon", 150.0, -20.0, 10.0),
        ("disc-70", 650.0, 0.0, 0.0),
        ("square-60", 650.0, 300.0, 44.0),
        ("rounded-rect-100x60", 650.0, -300.0, 91.0),
    ]
    rows = []
    for name, x, y, turn in placements:
        scene = Scene()
        scene.place_workpiece(name, x, y, turn)
        stages: dict[str, list[float]] = {
            k: [] for k in ("undistort", "markers", "find", "to_mm", "match", "plan")
        }
        centre_error = turn_error = 0.0
        for repeat in range(repeats):
            raw = render_table(scene, rng=np.random.default_rng(100 + repeat))
            image, t = timed(undistorter, raw)
            stages["undistort"].append(t)
            found, t = timed(detector.detect, image)
            stages["markers"].append(t)
            exclude = [d.centre + (d.corners - d.centre) * EXCLUSION_SCALE for d in found.values()]
            contours, t = timed(find_outlines, image, exclude=exclude)
            stages["find"].append(t)
            outline, t = timed(outline_to_mm, contours[0], homography)
            stages["to_mm"].append(t)
            match, t = timed(match_outline, outline, library)
            stages["match"].append(t)
            assert match is not None and match.workpiece_id == name
            placed = transform_outline(library[name], match.transform)
            _, t = timed(spray_polylines, placed, pattern)
            stages["plan"].append(t)
            pose = outline_pose(outline)
            centre_error = max(centre_error, math.hypot(pose.x - x, pose.y - y))
            symmetry = WORKPIECE_SHAPES[name].symmetry_deg
            if symmetry > 0:
                diff = (match.rotation_deg - turn) % symmetry
                turn_error = max(turn_error, min(diff, symmetry - diff))
        row: dict[str, Any] = {"workpiece": f"{name} at {turn:g}°"}
        for stage, values in stages.items():
            row[f"{stage}_p50_ms"] = percentiles_ms(values)["p50_ms"]
        row["find+match_p50_ms"] = round(
            percentiles_ms(
                [
                    a + b + c
                    for a, b, c in zip(
                        stages["find"], stages["to_mm"], stages["match"], strict=True
                    )
                ]
            )["p50_ms"],
            3,
        )
        row["centroid_error_max_mm"] = round(centre_error, 4)
        row["rotation_error_max_deg"] = (
            round(turn_error, 4) if WORKPIECE_SHAPES[name].symmetry_deg else None
        )
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--frames", type=int, default=60, help="frames for marker detection")
    parser.add_argument("--repeats", type=int, default=10, help="frames per workpiece")
    args = parser.parse_args(argv)
    extra = {"opencv": cv2.__version__, "cv2_threads": cv2.getNumThreads()}
    detection = [row for px in MARKER_SIZES_MM for row in detection_rows(args.frames, px)]
    emit("vision_detection", detection, {"frames": args.frames, **extra})
    calibration = calibration_rows()
    emit("vision_calibration", calibration, extra)
    workpieces = workpiece_rows(args.repeats)
    emit("vision_workpieces", workpieces, {"repeats": args.repeats, **extra})
    return detection + calibration + workpieces


if __name__ == "__main__":
    main()
