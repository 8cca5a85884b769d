"""Chessboard views for intrinsic calibration, rendered through the exact camera model.

Intrinsic calibration needs a flat board seen at several well-spread, tilted poses. Each view
is formed like the table view (see camera_scene): the board is drawn in its own plane at
0.1 mm per pixel (square edges fall exactly on pixel boundaries, so the drawing is exact),
band-limited by the camera pixel's footprint at the board's distance plus lens blur, then
sampled where each camera pixel's ray meets the board plane, distortion included.

Poses follow OpenCV's convention so results compare one-to-one with `cv2.calibrateCamera`:
`X_cam = R · X_board + t`, board frame origin at the first inner corner, x along a row of
inner corners, y down the columns, z into the board.
"""

from __future__ import annotations

import functools
import logging
import math
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

from server.drivers.sim.camera_model import (
    DEFAULT_CAMERA_MODEL,
    CameraModel,
    expose,
    footprint_blur_sigma_px,
    lighting_gain,
    normalised_pixel_grid,
)

logger = logging.getLogger(__name__)

BOARD_MM_PER_PX = 0.1
BOARD_WHITE = 235.0
BOARD_BLACK = 22.0
BACKDROP = 70.0  # what is seen around the board: the dark table far below


@dataclass(frozen=True)
class Chessboard:
    """A printed calibration board: `cols` × `rows` inner corners, squares of `square_mm`.

    The printed area is (cols + 1) × (rows + 1) squares with a white margin around it, which
    `cv2.findChessboardCorners` needs to find the outer squares.
    """

    cols: int = 9
    rows: int = 6
    square_mm: float = 30.0
    margin_mm: float = 20.0

    @property
    def pattern_size(self) -> tuple[int, int]:
        """(cols, rows), the patternSize argument of cv2.findChessboardCorners."""
        return self.cols, self.rows

    def object_points(self) -> NDArray[np.float32]:
        """Inner corners in the board frame (N×3, mm), row by row as OpenCV reports them."""
        grid = np.mgrid[0 : self.cols, 0 : self.rows].T.reshape(-1, 2) * self.square_mm
        return np.hstack([grid, np.zeros((len(grid), 1))]).astype(np.float32)

    def plate_corners_mm(self) -> NDArray[np.float64]:
        """Corners of the board's outer edge (4×3, board frame)."""
        lo = -self.square_mm - self.margin_mm
        hx = self.cols * self.square_mm + self.margin_mm
        hy = self.rows * self.square_mm + self.margin_mm
        return np.array([[lo, lo, 0.0], [hx, lo, 0.0], [hx, hy, 0.0], [lo, hy, 0.0]])

    @property
    def centre_mm(self) -> NDArray[np.float64]:
        """Centre of the inner-corner grid in the board frame."""
        return np.array([(self.cols - 1) / 2.0, (self.rows - 1) / 2.0, 0.0]) * self.square_mm


DEFAULT_CHESSBOARD = Chessboard()


@dataclass(frozen=True)
class BoardPose:
    """Board → camera transform (OpenCV convention: rvec as Rodrigues vector, tvec in mm)."""

    rvec: tuple[float, float, float]
    tvec: tuple[float, float, float]

    @property
    def rotation(self) -> NDArray[np.float64]:
        matrix, _ = cv2.Rodrigues(np.asarray(self.rvec, dtype=np.float64))
        return cast(NDArray[np.float64], matrix)

    def to_camera(self, points_board: NDArray) -> NDArray[np.float64]:
        """Board-frame points (N×3) in the camera frame."""
        return np.asarray(points_board, dtype=np.float64) @ self.rotation.T + self.tvec


def chessboard_corner_pixels(
    model: CameraModel, board: Chessboard, pose: BoardPose
) -> NDArray[np.float64]:
    """Ground truth: where the inner corners appear (N×2 px, object_points() order)."""
    return model.project_camera_frame(pose.to_camera(board.object_points()))


def _aimed_pose(
    model: CameraModel,
    board: Chessboard,
    at_px: tuple[float, float],
    distance_mm: float,
    tilt_x_deg: float,
    tilt_y_deg: float,
    spin_deg: float,
) -> BoardPose:
    """A board whose centre is seen at pixel `at_px`, `distance_mm` along the optical axis."""
    rot = (
        cv2.Rodrigues(np.array([0.0, 0.0, math.radians(spin_deg)]))[0]
        @ cv2.Rodrigues(np.array([0.0, math.radians(tilt_y_deg), 0.0]))[0]
        @ cv2.Rodrigues(np.array([math.radians(tilt_x_deg), 0.0, 0.0]))[0]
    )
    ray = model.pixel_to_normalised(np.asarray(at_px, dtype=np.float64))
    centre_cam = distance_mm * np.array([ray[0], ray[1], 1.0])
    tvec = centre_cam - rot @ board.centre_mm
    rvec, _ = cv2.Rodrigues(rot)
    return BoardPose(tuple(float(v) for v in rvec.ravel()), tuple(float(v) for v in tvec))  # type: ignore[arg-type]


# (centre u, centre v, distance mm, tilt about x°, tilt about y°, spin°): the board held
# tilted 20-35° in different directions, covering the centre, edges and corners of the image.
_DEFAULT_VIEWS: tuple[tuple[float, float, float, float, float, float], ...] = (
    (960, 540, 700, 25, 0, 5),
    (960, 540, 700, 0, -28, -5),
    (560, 350, 800, 22, -22, 10),
    (1360, 350, 800, 22, 22, -10),
    (560, 730, 800, -22, -22, -10),
    (1360, 730, 800, -22, 22, 10),
    (470, 540, 720, 0, 30, 3),
    (1450, 540, 720, 0, -30, -3),
    (960, 290, 740, -30, 0, 0),
    (960, 790, 740, 30, 0, 0),
    (960, 540, 640, 20, 20, 30),
    (960, 540, 680, -20, -25, -25),
)


@functools.lru_cache(maxsize=4)
def default_chessboard_poses(
    model: CameraModel = DEFAULT_CAMERA_MODEL, board: Chessboard = DEFAULT_CHESSBOARD
) -> tuple[BoardPose, ...]:
    """Twelve well-conditioned board poses, each fully in view with margin to spare."""
    poses = tuple(
        _aimed_pose(model, board, (u, v), d, tx, ty, sp) for u, v, d, tx, ty, sp in _DEFAULT_VIEWS
    )
    for index, pose in enumerate(poses):
        plate = model.project_camera_frame(pose.to_camera(board.plate_corners_mm()))
        if not (
            (plate >= 5).all()
            and (plate[:, 0] <= model.width - 6).all()
            and (plate[:, 1] <= model.height - 6).all()
        ):
            logger.warning("default chessboard view %d is not fully inside the image", index)
    return poses


@functools.lru_cache(maxsize=2)
def _board_texture(board: Chessboard) -> tuple[NDArray[np.uint8], float, float]:
    """The board drawn in its own plane: image, and board coordinates of pixel (0, 0)'s centre."""
    res = BOARD_MM_PER_PX
    surround = 10.0  # mm of backdrop around the plate, so blurring sees the plate's edge
    lo = -board.square_mm - board.margin_mm - surround
    cols = round((board.cols * board.square_mm + board.margin_mm + surround - lo) / res)
    rows = round((board.rows * board.square_mm + board.margin_mm + surround - lo) / res)
    origin = lo + res / 2.0  # pixel edges, hence square edges, fall on multiples of res
    bx = origin + np.arange(cols) * res
    by = origin + np.arange(rows) * res
    sq_x = np.floor(bx / board.square_mm).astype(np.int64) + 1  # 0..cols: printed squares
    sq_y = np.floor(by / board.square_mm).astype(np.int64) + 1
    in_x = (sq_x >= 0) & (sq_x <= board.cols)
    in_y = (sq_y >= 0) & (sq_y <= board.rows)
    # a square is black where its column and row numbers have the same parity; worked
    # out per column and per row, then crossed as bytes (the texture has ~10 M pixels)
    odd_x = (sq_x & 1).astype(np.uint8)
    odd_y = (sq_y & 1).astype(np.uint8)
    black = (odd_x[None, :] == odd_y[:, None]) & in_x[None, :] & in_y[:, None]
    plate_lo, plate_x = -board.square_mm - board.margin_mm, board.cols * board.square_mm
    plate = ((bx >= plate_lo) & (bx < plate_x + board.margin_mm))[None, :] & (
        (by >= plate_lo) & (by < board.rows * board.square_mm + board.margin_mm)
    )[:, None]
    texture = np.full((rows, cols), BACKDROP, dtype=np.float32)
    texture[plate] = BOARD_WHITE
    texture[black] = BOARD_BLACK
    return texture.astype(np.uint8), origin, origin


_view_lock = threading.Lock()
_view_cache: OrderedDict[tuple, NDArray[np.uint8]] = OrderedDict()


def _ray_to_texture(pose: BoardPose, origin_x: float, origin_y: float) -> NDArray[np.float64]:
    """The homography from a camera ray (x, y, 1) to the board texture's pixel (u, v, 1).

    A board point (bx, by, 0) is seen along the ray [r1 r2 t]·(bx, by, 1) (r1, r2: the
    first two columns of R), so the inverse of that matrix takes a ray back to the
    board, where 1/depth is left as the third coordinate; then mm to texture pixels.
    """
    rot, tvec = pose.rotation, np.asarray(pose.tvec, dtype=np.float64)
    ray_of_board = np.column_stack([rot[:, 0], rot[:, 1], tvec])
    res = BOARD_MM_PER_PX
    mm_to_texture = np.array(
        [[1.0 / res, 0.0, -origin_x / res], [0.0, 1.0 / res, -origin_y / res], [0.0, 0.0, 1.0]]
    )
    return cast(NDArray[np.float64], mm_to_texture @ np.linalg.inv(ray_of_board))


def _clean_view(model: CameraModel, board: Chessboard, pose: BoardPose) -> NDArray[np.uint8]:
    """The noiseless, unlit grey view of one pose (cached: views repeat as the camera cycles)."""
    key = (model, board, pose)
    with _view_lock:
        if key in _view_cache:
            _view_cache.move_to_end(key)
            return _view_cache[key]
    texture, origin_x, origin_y = _board_texture(board)
    rays = normalised_pixel_grid(model)
    to_texture = _ray_to_texture(pose, origin_x, origin_y)
    maps = cv2.perspectiveTransform(rays.reshape(-1, 1, 2), to_texture)
    maps = maps.reshape(*rays.shape[:2], 2).astype(np.float32)
    # The third homogeneous coordinate is 1/depth: a ray meeting the board's plane behind
    # the camera (or never) sees the backdrop.
    inverse_depth = to_texture[2, 0] * rays[..., 0] + to_texture[2, 1] * rays[..., 1]
    inverse_depth += to_texture[2, 2]
    behind = ~(inverse_depth > 0)
    if behind.any():
        maps[behind] = -10.0
    distance = float(np.linalg.norm(pose.to_camera(board.centre_mm[None, :])))
    footprint_mm = distance / math.sqrt(model.fx * model.fy)
    sigma = footprint_blur_sigma_px() * footprint_mm / BOARD_MM_PER_PX
    blurred = cv2.GaussianBlur(texture, (0, 0), sigma)
    view = cast(
        NDArray[np.uint8],
        cv2.remap(
            blurred,
            maps[..., 0],
            maps[..., 1],
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=BACKDROP,
        ),
    )
    with _view_lock:
        _view_cache[key] = view
        while len(_view_cache) > 16:  # 2 MB each; the default cycle has 12
            _view_cache.popitem(last=False)
    return view


def render_chessboard_view(
    model: CameraModel = DEFAULT_CAMERA_MODEL,
    board: Chessboard = DEFAULT_CHESSBOARD,
    pose: BoardPose | None = None,
    *,
    noise_sigma: float = 2.0,
    vignetting: float = 0.12,
    light_gradient: float = 0.05,
    rng: np.random.Generator | None = None,
) -> NDArray[np.uint8]:
    """One camera frame (uint8 BGR) of the board at `pose` (default: the first default pose)."""
    if pose is None:
        pose = default_chessboard_poses(model, board)[0]
    view = _clean_view(model, board, pose)
    lit = view.astype(np.float32)[..., None] * lighting_gain(model, vignetting, light_gradient)
    clean = np.repeat(lit, 3, axis=2)
    return expose(clean, noise_sigma, rng or np.random.default_rng(0))


def clear_chessboard_cache() -> None:
    """Drop cached views (~2 MB each) and the board's texture."""
    with _view_lock:
        _view_cache.clear()
    _board_texture.cache_clear()
