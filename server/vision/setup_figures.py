"""Focus and exposure figures of a frame, for setting the camera up before calibrating.

A technician turns the focus ring and the lights until these are good, then calibrates:

- sharpness: the variance of the Laplacian of the grey frame. Edges in focus give large
  second derivatives, blur flattens them, so the figure peaks at best focus. It has no
  absolute scale (it depends on the scene and on sensor noise): compare it while turning
  the ring on the same table, and keep the best.
- brightness: the mean grey level (0-255). The markers need a white quiet zone that is not
  clipped and a black square that is not lost in noise: mid-range is right.
- clipped: the percentage of pixels at 255 (over-exposed: a marker's white border lost in
  glare is a marker not found), at 0 the percentage under-exposed.

Pure functions on arrays: no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from server.vision.markers import to_gray


@dataclass(frozen=True, slots=True)
class FocusFigures:
    """What `measure` found on one frame."""

    sharpness: float  # variance of the Laplacian, grey levels²
    brightness: float  # mean grey level, 0-255
    over_exposed_pct: float  # pixels at 255, % of the frame
    under_exposed_pct: float  # pixels at 0, % of the frame


def measure(image: np.ndarray) -> FocusFigures:
    """Sharpness and exposure of a BGR or grey frame (see the module's docstring)."""
    gray = to_gray(image)
    laplacian = cv2.Laplacian(gray, cv2.CV_32F)
    _, stddev = cv2.meanStdDev(laplacian)
    pixels = float(gray.size) or 1.0
    return FocusFigures(
        sharpness=round(float(stddev[0][0]) ** 2, 1),
        brightness=round(float(cv2.mean(gray)[0]), 1),
        over_exposed_pct=round(100.0 * float(np.count_nonzero(gray == 255)) / pixels, 2),
        under_exposed_pct=round(100.0 * float(np.count_nonzero(gray == 0)) / pixels, 2),
    )
