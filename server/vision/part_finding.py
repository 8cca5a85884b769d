"""The image process's part of teaching and finding workpieces: the outlines in a frame,
in millimetres, and which library part each one is.

Apart from the operations (`server/core/operations/workpieces.py`) because these
run in the image process (`server.vision.process`), which imports the module of
each function it is handed, and what they return crosses back pickled: plain
arrays, bytes and dicts, so the image process of a cell with a real camera holds
OpenCV and numpy, not the server's settings, models and operations.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from server.vision.outlines import (
    match_outline,
    outline_to_mm,
    part_outlines_px,
    transform_outline,
)

THUMBNAIL_PX = 256


def thumbnail(frame: np.ndarray, contour_px: np.ndarray) -> bytes:
    """The part's crop with a margin, at most THUMBNAIL_PX a side, as PNG."""
    x, y, w, h = cv2.boundingRect(contour_px.astype(np.float32))
    margin = max(w, h) // 10 + 4
    crop = frame[max(0, y - margin) : y + h + margin, max(0, x - margin) : x + w + margin]
    scale = THUMBNAIL_PX / max(crop.shape[:2])
    if scale < 1:
        crop = cv2.resize(crop, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    ok, png = cv2.imencode(".png", crop)
    return png.tobytes() if ok else b""


def measure_part(
    frame: np.ndarray, homography: np.ndarray, library: dict[str, np.ndarray]
) -> tuple[np.ndarray, bytes, dict[str, Any] | None] | None:
    """The largest part's outline (mm), its thumbnail (PNG) and the stored part it matches
    (id, score, fit error), if any; None when no part is on the table."""
    outlines = part_outlines_px(frame)
    if not outlines:
        return None
    outline_mm = outline_to_mm(outlines[0], homography)
    match = match_outline(outline_mm, library) if library else None
    similar = (
        None
        if match is None
        else {
            "workpiece_id": match.workpiece_id,
            "score": round(match.score, 5),
            "fit_error_mm": round(match.fit_error_mm, 3),
        }
    )
    return outline_mm, thumbnail(frame, outlines[0]), similar


def match_parts(
    frame: np.ndarray, homography: np.ndarray, library: dict[str, np.ndarray]
) -> list[tuple[str, np.ndarray, dict[str, Any]]]:
    """Each part outline in the frame matched to the library: its workpiece id, the
    library outline placed where the part lies (mm), and the match's figures."""
    found = []
    for contour in part_outlines_px(frame):
        detected = outline_to_mm(contour, homography)
        match = match_outline(detected, library)
        if match is None:
            continue
        placed = transform_outline(library[match.workpiece_id], match.transform)
        figures = {
            "score": round(match.score, 5),
            "rotation_deg": round(match.rotation_deg, 3),
            "translation_mm": [round(v, 3) for v in match.translation_mm],
            "fit_error_mm": round(match.fit_error_mm, 3),
        }
        found.append((match.workpiece_id, placed, figures))
    return found
