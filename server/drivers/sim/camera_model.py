"""The simulated cell camera's geometry and sensor: a known model to check vision against.

The vision code later claims 0.5 mm (markers), 2 % focal length (chessboard calibration) and
1 mm / 1° (workpieces). Those claims are only honest if the simulator's camera is known
*exactly*, so this module owns one explicit model: a pinhole with OpenCV's Brown–Conrady
distortion (k1, k2, p1, p2, k3 — the same formula `cv2.projectPoints` uses, so OpenCV
calibration results compare one-to-one) mounted at a known pose above the table.

Rendering needs the *inverse* mapping (pixel → table) for every one of the ~2 million pixels,
to sub-micrometre precision. `cv2.undistortPoints` stops after a handful of fixed-point
iterations, so the inverse here is a Newton solve run to machine precision.

Frames: robot base frame in mm, table plane z = 0. Camera frame as in OpenCV: x right, y down,
z along the optical axis; `X_cam = R · X_robot + t` with `R = Rodrigues(rvec)`.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

logger = logging.getLogger(__name__)

IMAGE_WIDTH = 1920
IMAGE_HEIGHT = 1080

# Optical blur of the lens, as the standard deviation of a Gaussian in pixels. Together with
# the pixel's own area it band-limits the scene before sampling, which is what lets edges and
# corners be located to a small fraction of a pixel (as with a real, slightly soft lens).
LENS_BLUR_SIGMA_PX = 0.5
# Points per block of the undistortion's Newton steps (CameraModel.undistort). A block's
# temporaries (64 KiB of float64 each) stay in the CPU's cache and come from the heap: the
# server and its image process map every block of 128 KiB or more apart and unmap it when
# freed (server/common/runtime.py, MMAP_THRESHOLD), so a block twice this size made each
# temporary fault its pages in again and cost as much as the whole array at once.
NEWTON_BLOCK = 1 << 13

Array = NDArray[np.float64]


def _rotation_about(axis: Sequence[float], angle_deg: float) -> Array:
    """Rotation matrix for `angle_deg` about `axis` (right-hand rule)."""
    axis_arr = np.asarray(axis, dtype=np.float64)
    rvec = axis_arr / np.linalg.norm(axis_arr) * math.radians(angle_deg)
    matrix, _ = cv2.Rodrigues(rvec)
    return cast(Array, matrix)


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics, distortion and mounting pose of one camera; immutable and hashable.

    Hashable so render caches (per-pixel ray maps) can be keyed on the model itself; change
    a value with `dataclasses.replace`.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float]  # k1, k2, p1, p2, k3 (OpenCV's order)
    rvec: tuple[float, float, float]  # robot → camera rotation (Rodrigues)
    tvec: tuple[float, float, float]  # robot → camera translation, mm
    width: int = IMAGE_WIDTH
    height: int = IMAGE_HEIGHT

    def __post_init__(self) -> None:
        coeffs = tuple(float(c) for c in self.dist)
        if len(coeffs) == 4:
            coeffs = (*coeffs, 0.0)
        if len(coeffs) != 5:
            raise ValueError(f"dist is (k1, k2, p1, p2[, k3]), got {len(coeffs)} values")
        # normalise to plain floats/tuples so numpy inputs still give a hashable model
        for name in ("fx", "fy", "cx", "cy"):
            object.__setattr__(self, name, float(getattr(self, name)))
        object.__setattr__(self, "dist", coeffs)
        object.__setattr__(self, "rvec", tuple(float(v) for v in np.ravel(self.rvec)))
        object.__setattr__(self, "tvec", tuple(float(v) for v in np.ravel(self.tvec)))
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    # --- construction ---------------------------------------------------------------------

    @classmethod
    def looking_at(
        cls,
        position_mm: Sequence[float],
        target_mm: Sequence[float],
        *,
        roll_deg: float = 0.0,
        image_down: Sequence[float] = (1.0, 0.0, 0.0),
        fx: float,
        fy: float,
        cx: float,
        cy: float,
        dist: Sequence[float] = (0.0, 0.0, 0.0, 0.0, 0.0),
        width: int = IMAGE_WIDTH,
        height: int = IMAGE_HEIGHT,
    ) -> CameraModel:
        """A camera at `position_mm` aimed at `target_mm`, the way it is mounted in the cell.

        `image_down` is the robot direction that should point down the image (+v) before
        `roll_deg` turns the camera about its optical axis.
        """
        centre = np.asarray(position_mm, dtype=np.float64)
        z_cam = np.asarray(target_mm, dtype=np.float64) - centre
        z_cam /= np.linalg.norm(z_cam)
        down = np.asarray(image_down, dtype=np.float64)
        y_cam = down - (down @ z_cam) * z_cam
        y_cam /= np.linalg.norm(y_cam)
        x_cam = np.cross(y_cam, z_cam)
        rotation = _rotation_about((0.0, 0.0, 1.0), roll_deg) @ np.vstack([x_cam, y_cam, z_cam])
        rvec, _ = cv2.Rodrigues(rotation)
        tvec = -rotation @ centre
        return cls(
            fx,
            fy,
            cx,
            cy,
            cast(tuple[float, float, float, float, float], tuple(dist)),
            cast(tuple[float, float, float], tuple(rvec.ravel())),
            cast(tuple[float, float, float], tuple(tvec)),
            width,
            height,
        )

    @classmethod
    def default(cls) -> CameraModel:
        """The simulated cell camera: 1920×1080, f = 1400 px, ~900 mm above the table.

        Slightly off-centre and tilted (~2.9°) and rolled (1.5°) on purpose, so that vision code
        that silently assumes a perfectly square-on camera fails against the simulator too.
        It sees the table over about x 50..750 mm, y -600..600 mm.
        """
        return cls.looking_at(
            (370.0, 20.0, 900.0),
            (400.0, 0.0, 0.0),
            roll_deg=1.5,
            fx=1400.0,
            fy=1400.0,
            cx=962.5,
            cy=537.0,
            dist=(-0.05, 0.02, 0.0005, -0.0003, 0.0),
        )

    # --- derived quantities ---------------------------------------------------------------

    @property
    def camera_matrix(self) -> Array:
        """The 3×3 intrinsic matrix K, as OpenCV's calibrateCamera returns it."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> Array:
        """(k1, k2, p1, p2, k3), OpenCV's order."""
        return np.array(self.dist, dtype=np.float64)

    @property
    def rotation(self) -> Array:
        """R with X_cam = R · X_robot + t."""
        matrix, _ = cv2.Rodrigues(np.array(self.rvec, dtype=np.float64))
        return cast(Array, matrix)

    @property
    def position_mm(self) -> Array:
        """Camera centre in the robot base frame."""
        return -self.rotation.T @ np.array(self.tvec, dtype=np.float64)

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.width, self.height

    # --- forward: world → pixel -----------------------------------------------------------

    def distort(self, normalised: ArrayLike) -> Array:
        """Apply lens distortion to ideal normalised coordinates (x/z, y/z)."""
        xy = np.asarray(normalised, dtype=np.float64)
        x, y = xy[..., 0], xy[..., 1]
        k1, k2, p1, p2, k3 = self.dist
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return np.stack([xd, yd], axis=-1)

    def project_camera_frame(self, points_cam: ArrayLike) -> Array:
        """Pixels (…×2) of points given in the camera frame (…×3), with distortion."""
        pts = np.asarray(points_cam, dtype=np.float64)
        normalised = pts[..., :2] / pts[..., 2:3]
        distorted = self.distort(normalised)
        u = self.fx * distorted[..., 0] + self.cx
        v = self.fy * distorted[..., 1] + self.cy
        return np.stack([u, v], axis=-1)

    def to_camera_frame(self, points_robot_mm: ArrayLike) -> Array:
        """Robot-frame points (…×3) expressed in the camera frame."""
        pts = np.asarray(points_robot_mm, dtype=np.float64)
        return pts @ self.rotation.T + np.array(self.tvec)

    def project(self, points_robot_mm: ArrayLike) -> Array:
        """Pixels (…×2) where robot-frame points (…×3, mm) appear, distortion included."""
        return self.project_camera_frame(self.to_camera_frame(points_robot_mm))

    def table_to_pixel(self, table_xy_mm: ArrayLike, z_mm: float = 0.0) -> Array:
        """Pixels (…×2) of table points (…×2, mm) on the plane z = `z_mm`."""
        xy = np.asarray(table_xy_mm, dtype=np.float64)
        z = np.full((*xy.shape[:-1], 1), float(z_mm))
        return self.project(np.concatenate([xy, z], axis=-1))

    # --- inverse: pixel → world -----------------------------------------------------------

    def undistort(self, distorted: ArrayLike, *, max_iterations: int = 30) -> Array:
        """Ideal normalised coordinates whose distortion gives `distorted` (Newton, to 1e-15).

        Every point takes the same steps, until the largest step of all is below 1e-15. A
        step is computed block by block (`NEWTON_BLOCK` points): on a frame's two million
        pixels, a step over the whole array at once makes each of its twenty temporaries a
        fresh 16 MB mapping, and faulting those in cost twice the arithmetic. The result
        does not depend on the block size, to the bit.
        """
        target = np.asarray(distorted, dtype=np.float64)
        tx = np.ascontiguousarray(target[..., 0]).reshape(-1)
        ty = np.ascontiguousarray(target[..., 1]).reshape(-1)
        x, y = tx.copy(), ty.copy()
        for _ in range(max_iterations):
            largest = 0.0
            for start in range(0, x.size, NEWTON_BLOCK):
                block = slice(start, start + NEWTON_BLOCK)
                step_x, step_y = self._newton_step(x[block], y[block], tx[block], ty[block])
                x[block] -= step_x
                y[block] -= step_y
                largest = max(
                    largest,
                    float(np.max(np.abs(step_x), initial=0.0)),
                    float(np.max(np.abs(step_y), initial=0.0)),
                )
            if largest < 1e-15:
                break
        return np.stack([x, y], axis=-1).reshape(target.shape)

    def _newton_step(self, x: Array, y: Array, tx: Array, ty: Array) -> tuple[Array, Array]:
        """One Newton step of `distort(x, y) = (tx, ty)`: what to subtract from x and y."""
        k1, k2, p1, p2, k3 = self.dist
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        d_radial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        res_x = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - tx
        res_y = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - ty
        j_xx = radial + 2.0 * x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x
        j_xy = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
        j_yy = radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x
        det = j_xx * j_yy - j_xy * j_xy
        return (j_yy * res_x - j_xy * res_y) / det, (j_xx * res_y - j_xy * res_x) / det

    def pixel_to_normalised(self, pixels: ArrayLike) -> Array:
        """Undistorted normalised coordinates (ray direction (x, y, 1)) of pixels (…×2)."""
        px = np.asarray(pixels, dtype=np.float64)
        distorted = np.stack(
            [(px[..., 0] - self.cx) / self.fx, (px[..., 1] - self.cy) / self.fy], axis=-1
        )
        return self.undistort(distorted)

    def rays_to_table(self, normalised: ArrayLike, z_mm: float = 0.0) -> Array:
        """Where camera rays (x, y, 1) meet the plane z = `z_mm`: robot (x, y) in mm."""
        xy = np.asarray(normalised, dtype=np.float64)
        rot_t = self.rotation.T
        centre = self.position_mm
        # direction in the robot frame = Rᵀ · (x, y, 1), written out to avoid a 3-vector copy
        dx = rot_t[0, 0] * xy[..., 0] + rot_t[0, 1] * xy[..., 1] + rot_t[0, 2]
        dy = rot_t[1, 0] * xy[..., 0] + rot_t[1, 1] * xy[..., 1] + rot_t[1, 2]
        dz = rot_t[2, 0] * xy[..., 0] + rot_t[2, 1] * xy[..., 1] + rot_t[2, 2]
        scale = (float(z_mm) - centre[2]) / dz
        return np.stack([centre[0] + scale * dx, centre[1] + scale * dy], axis=-1)

    def pixel_to_table(self, pixels: ArrayLike, z_mm: float = 0.0) -> Array:
        """Table point (robot x, y in mm on the plane z = `z_mm`) seen at each pixel (…×2)."""
        return self.rays_to_table(self.pixel_to_normalised(pixels), z_mm)

    def sees(self, points_robot_mm: ArrayLike, margin_px: float = 0.0) -> NDArray[np.bool_]:
        """True for points in front of the camera that land inside the image (with margin)."""
        cam = self.to_camera_frame(points_robot_mm)
        px = self.project_camera_frame(cam)
        return (
            (cam[..., 2] > 0)
            & (px[..., 0] >= margin_px)
            & (px[..., 0] <= self.width - 1 - margin_px)
            & (px[..., 1] >= margin_px)
            & (px[..., 1] <= self.height - 1 - margin_px)
        )


DEFAULT_CAMERA_MODEL = CameraModel.default()


def shifted_camera(model: CameraModel, dx_mm: float, dy_mm: float) -> CameraModel:
    """The same camera moved by dx, dy mm parallel to the table (a knocked mounting): its
    centre moves, its orientation stays, so the whole table appears displaced."""
    move = model.rotation @ np.array([float(dx_mm), float(dy_mm), 0.0])
    tvec = np.asarray(model.tvec, dtype=np.float64) - move
    return dataclasses.replace(model, tvec=(float(tvec[0]), float(tvec[1]), float(tvec[2])))


# --- per-model caches shared by the renderers ----------------------------------------------


@functools.lru_cache(maxsize=4)
def normalised_pixel_grid(model: CameraModel) -> Array:
    """Undistorted normalised ray (x, y) of every pixel centre, H×W×2; cached per model.

    Pixel (row v, column u) is centred at (u, v), OpenCV's convention, so renders and
    `project` agree to the bit.
    """
    u, v = np.meshgrid(
        np.arange(model.width, dtype=np.float64), np.arange(model.height, dtype=np.float64)
    )
    grid = model.pixel_to_normalised(np.stack([u, v], axis=-1))
    grid.setflags(write=False)
    logger.debug("computed the undistorted ray of every pixel for %r", model)
    return grid


@functools.lru_cache(maxsize=8)
def lighting_gain(model: CameraModel, vignetting: float, light_gradient: float) -> NDArray:
    """Per-pixel brightness factor (H×W×1, float32): lens vignetting and uneven cell lighting.

    `vignetting` is the fractional drop in the image corners; `light_gradient` the fractional
    change from the left to the right edge (a lamp off to one side). Thresholds and marker
    detection must cope with both on a real cell, so the simulator does not hide them.
    """
    u, v = np.meshgrid(
        np.arange(model.width, dtype=np.float32), np.arange(model.height, dtype=np.float32)
    )
    corner_r2 = (
        max(model.cx, model.width - model.cx) ** 2 + max(model.cy, model.height - model.cy) ** 2
    )
    r2 = ((u - model.cx) ** 2 + (v - model.cy) ** 2) / corner_r2
    gain = (1.0 - vignetting * r2) * (1.0 + light_gradient * (u / model.width - 0.5))
    gain32 = gain.astype(np.float32)[..., None]
    gain32.setflags(write=False)
    return gain32


def expose(clean: NDArray, noise_sigma: float, rng: np.random.Generator) -> NDArray[np.uint8]:
    """The sensor's read-out: add Gaussian noise (per pixel and channel) and quantise to uint8.

    `clean` is the float32 H×W×3 irradiance in grey levels. The noise comes from OpenCV's
    thread-local RNG (4× faster than numpy's here) seeded from `rng`, so frames stay
    reproducible for a given seed whichever worker thread renders them.
    """
    frame = np.empty_like(clean)
    if noise_sigma > 0:
        cv2.setRNGSeed(int(rng.integers(0, 2**31 - 1)))
        noise = np.empty_like(clean)
        # OpenCV takes a Scalar (a tuple) for mean and stddev here and in cv2.max; its stubs do not.
        cv2.randn(noise, (0.0, 0.0, 0.0), (noise_sigma, noise_sigma, noise_sigma))  # type: ignore[call-overload]
        cv2.add(clean, noise, dst=frame)
    else:
        frame[...] = clean
    cv2.max(frame, 0.0, dst=frame)  # type: ignore[call-overload]
    return cast(NDArray[np.uint8], cv2.convertScaleAbs(frame))  # rounds and saturates at 255


def footprint_blur_sigma_px() -> float:
    """Blur (in output pixels) that stands for the pixel's area plus the lens: √(1/12 + σ²)."""
    return math.sqrt(1.0 / 12.0 + LENS_BLUR_SIGMA_PX**2)
