"""What a real table does to the simulated camera's frame: off by default, set per scene.

The simulator's geometry is exact, so accuracy measured on its clean frames says how good the
vision code is, not how good the cell will be. A real table adds what no model fitted at
commissioning removes: lens distortion beyond the five Brown–Conrady terms, a lens slightly
out of focus, light that is uneven across the table, more sensor noise, JPEG compression on
the way from the camera, and marker sheets printed a little off scale. `Degradations` holds
one figure for each, 0 (or 1 for the scale) meaning "as the clean simulator"; a `Scene`
carries one (`Scene.degradations`) and `render_table` applies it.

Each is applied where it happens in a real camera, in this order on the lit frame: the print
scale when the markers are drawn (the sheets are larger, their centres where they were
placed), then the lens (blur, then the residual distortion), the light, the sensor's noise,
the compression. `distort_pixels` is the ground truth of the residual distortion: where a
point the exact model puts at a pixel really appears.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["Degradations", "light_field"]

# The residual distortion's waves across the image's width and down its height.
_WAVES_ACROSS = 1.5
_WAVES_DOWN = 1.25


@dataclass(frozen=True)
class Degradations:
    """How far a frame departs from the exact model; hashable (it keys the render caches).

    - `residual_distortion_px`: the lens's departure from the 5-coefficient model fitted at
      commissioning (a lens is not exactly Brown–Conrady; the fit leaves a smooth, wavy
      residual everywhere): a displacement of this amplitude along each axis, 1.5 waves
      across the width and 1.25 down the height, which no radial term or homography absorbs;
    - `blur_px`: Gaussian blur (σ, px) of a lens slightly out of focus;
    - `uneven_light`: a bright spot off-centre and a shadow across the table, as the
      fraction by which the light varies from the brightest place to the darkest;
    - `noise_sigma`: sensor noise (grey levels) in place of the scene's own;
    - `jpeg_quality`: 1..100, the frame compressed and decoded; 0 leaves it raw;
    - `print_scale`: every marker sheet printed at this scale (1.005 = 0.5 % too large).
    """

    residual_distortion_px: float = 0.0
    blur_px: float = 0.0
    uneven_light: float = 0.0
    noise_sigma: float | None = None
    jpeg_quality: int = 0
    print_scale: float = 1.0

    @classmethod
    def realistic(cls) -> Degradations:
        """All of them at once, at the size a commissioned real table shows."""
        return cls(
            residual_distortion_px=0.5,
            blur_px=0.8,
            uneven_light=0.3,
            noise_sigma=4.0,
            jpeg_quality=85,
            print_scale=1.005,
        )

    def distort_pixels(self, pixels: ArrayLike, size: tuple[int, int]) -> NDArray[np.float64]:
        """Where points the exact model projects to `pixels` (N×2) appear in the frame.

        `size` is (width, height). The identity when there is no residual distortion.
        """
        points = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        if self.residual_distortion_px == 0:
            return points
        width, height = size
        phase_x = 2.0 * np.pi * (_WAVES_ACROSS * points[:, 0] / width + 0.1)
        phase_y = 2.0 * np.pi * (_WAVES_DOWN * points[:, 1] / height + 0.2)
        shift = self.residual_distortion_px * np.stack([np.sin(phase_x), np.sin(phase_y)], axis=1)
        moved: NDArray[np.float64] = points + shift
        return moved

    def apply_to_light(self, frame: NDArray[np.float32]) -> NDArray[np.float32]:
        """Lens and light on the noiseless, lit float frame (H×W×3)."""
        height, width = frame.shape[:2]
        out = frame
        if self.blur_px > 0:
            out = cast(NDArray[np.float32], cv2.GaussianBlur(out, (0, 0), float(self.blur_px)))
        if self.residual_distortion_px != 0:
            map_x, map_y = _inverse_maps(float(self.residual_distortion_px), width, height)
            out = cast(
                NDArray[np.float32],
                cv2.remap(out, map_x, map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE),
            )
        if self.uneven_light > 0:
            out = out * light_field(float(self.uneven_light), width, height)[..., None]
        return out

    def apply_to_image(self, frame: NDArray[np.uint8]) -> NDArray[np.uint8]:
        """The camera's compression on the exposed 8-bit frame."""
        if not self.jpeg_quality:
            return frame
        ok, encoded = cv2.imencode(
            ".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, int(self.jpeg_quality)]
        )
        if not ok:
            raise RuntimeError("JPEG encoding of the simulated frame failed")
        return cast(NDArray[np.uint8], cv2.imdecode(encoded, cv2.IMREAD_UNCHANGED))


@functools.lru_cache(maxsize=2)
def _inverse_maps(amount_px: float, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """remap tables: for each frame pixel, the clean pixel it shows (fixed-point inverse of
    `distort_pixels`, converged far below a thousandth of a pixel for amounts of a few px)."""
    degradations = Degradations(residual_distortion_px=amount_px)
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    target = np.stack([xs.ravel(), ys.ravel()], axis=1)
    source = target.copy()
    for _ in range(6):
        source = source - (degradations.distort_pixels(source, (width, height)) - target)
    source = source.reshape(height, width, 2).astype(np.float32)
    return source[..., 0].copy(), source[..., 1].copy()


@functools.lru_cache(maxsize=2)
def light_field(amount: float, width: int, height: int) -> NDArray[np.float32]:
    """Gain (H×W) of uneven light: a spot up and left of centre, a shadow over the lower
    right, scaled so the brightest place is `amount` brighter than the darkest (relative to
    the brightest) and the mean is about 1."""
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    u, v = xs / width, ys / height
    spot = np.exp(-((u - 0.35) ** 2 + (v - 0.35) ** 2) / (2 * 0.25**2))
    shadow = 1.0 / (1.0 + np.exp(-(u + v - 1.5) / 0.08))
    field = spot - 0.6 * shadow
    field = (field - field.min()) / (field.max() - field.min())  # 0 darkest .. 1 brightest
    gain = 1.0 - amount * (1.0 - field)
    return (gain / gain.mean()).astype(np.float32)
