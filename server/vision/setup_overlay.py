"""The set-up view's picture: markers outlined and numbered, the workspace, the figures.

Drawn on a copy of the (undistorted) frame, then scaled down for the stream: the figures are
measured at full resolution before this, so the scaling changes only what is sent.
Pure functions on arrays: no I/O.
"""

from __future__ import annotations

from collections.abc import Mapping

import cv2
import numpy as np

from server.vision.homography import annotate_markers
from server.vision.markers import MarkerDetection

_WORKSPACE = (255, 200, 0)  # BGR: a cyan-blue no marker outline uses
_TEXT = (255, 255, 255)


def draw_setup_view(
    image: np.ndarray,
    detections: Mapping[int, MarkerDetection],
    workspace_px: np.ndarray | None,
    lines: list[str],
    *,
    width: int,
) -> np.ndarray:
    """The annotated frame, `width` pixels wide (never enlarged).

    `workspace_px` is the workspace's outline in the frame's pixels (N×2), or None when
    there is no map to draw it through; `lines` are written top left on a dark band.
    """
    out = annotate_markers(image, detections)
    scale = max(out.shape[:2]) / 1920.0
    thickness = max(1, round(3 * scale))
    if workspace_px is not None:
        polygon = np.round(np.asarray(workspace_px, dtype=np.float64)).astype(np.int32)
        cv2.polylines(out, [polygon], True, _WORKSPACE, thickness, cv2.LINE_AA)
    height, full_width = out.shape[:2]
    if full_width > width:
        out = cv2.resize(
            out, (width, round(height * width / full_width)), interpolation=cv2.INTER_AREA
        )
    # The numbers again, large enough to read at the stream's size (beside each marker).
    factor = out.shape[1] / full_width
    for marker_id, det in detections.items():
        corners = np.asarray(det.corners, dtype=np.float64).reshape(4, 2) * factor
        origin = (int(corners[:, 0].max()) + 4, int(corners[:, 1].min()) + 14)
        for colour, weight in (((0, 0, 0), 4), ((60, 200, 60), 2)):
            cv2.putText(out, str(marker_id), origin, cv2.FONT_HERSHEY_SIMPLEX, 0.6, colour, weight)
    line_height = 22
    band = 8 + line_height * len(lines)
    out[:band, : min(out.shape[1], 560)] //= 3  # darken, so the text reads on any table
    for i, text in enumerate(lines):
        origin = (8, 8 + line_height * i + 15)
        cv2.putText(out, text, origin, cv2.FONT_HERSHEY_SIMPLEX, 0.55, _TEXT, 1, cv2.LINE_AA)
    return out


def workspace_outline_mm(low: tuple[float, ...], high: tuple[float, ...]) -> np.ndarray:
    """The workspace's x-y rectangle on the table (4×2 mm), corner by corner."""
    (x0, y0), (x1, y1) = low[:2], high[:2]
    return np.array([(x0, y0), (x1, y0), (x1, y1), (x0, y1)], dtype=np.float64)
