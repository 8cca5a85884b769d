"""The set-up view's focus and exposure figures on synthetic frames (pure functions)."""

from __future__ import annotations

import cv2
import numpy as np

from server.vision.setup_figures import measure
from server.vision.setup_overlay import draw_setup_view, workspace_outline_mm


def checkerboard(size: int = 240, cell: int = 20) -> np.ndarray:
    ys, xs = np.indices((size, size))
    return np.where(((ys // cell) + (xs // cell)) % 2 == 0, 200, 40).astype(np.uint8)


def test_blur_lowers_the_sharpness_and_light_moves_the_brightness() -> None:
    sharp = checkerboard()
    blurred = cv2.GaussianBlur(sharp, (0, 0), 3.0)
    assert measure(blurred).sharpness < measure(sharp).sharpness / 4
    assert measure(sharp).brightness == 120.0
    dark = measure((sharp * 0.5).astype(np.uint8))
    assert dark.brightness == 60.0 and dark.over_exposed_pct == 0.0


def test_clipped_pixels_are_counted_both_ways() -> None:
    frame = np.zeros((10, 10, 3), np.uint8)
    frame[:3] = 255
    figures = measure(frame)
    assert figures.over_exposed_pct == 30.0 and figures.under_exposed_pct == 70.0


def test_the_picture_is_scaled_to_the_stream_width_and_never_enlarged() -> None:
    frame = cv2.cvtColor(checkerboard(400), cv2.COLOR_GRAY2BGR)
    outline = np.array([(10, 10), (300, 10), (300, 200), (10, 200)], float)
    small = draw_setup_view(frame, {}, outline, ["markers 0 of 9"], width=200)
    assert small.shape == (200, 200, 3)
    same = draw_setup_view(frame, {}, None, [], width=960)
    assert same.shape == frame.shape
    assert workspace_outline_mm((100, -400, 0), (800, 400, 5)).tolist() == [
        [100, -400],
        [800, -400],
        [800, 400],
        [100, 400],
    ]
