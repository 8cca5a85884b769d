"""The latest camera frame an operation captured, kept in memory for the HMI.

Every vision operation measures on an undistorted frame (see
`server.core.operations.camera_frames.capture_undistorted`); the last of them
is kept here, with when it was taken and by which operation, so the dashboard
can draw the planned path over what the camera saw for this run rather than
over the image of the last robot calibration (GET /camera/frame).

One frame at a time (about 6 MB at 1920×1080), replaced by the next capture,
never written to disk. The frame is kept by reference: operations treat their
frames as read-only (the annotated calibration image and thumbnails are
copies). The JPEG of a frame is made once, off the event loop, and reused by
every request until a newer frame arrives.
"""

from __future__ import annotations

import itertools
import threading
import time
from dataclasses import dataclass

import cv2
import numpy as np

JPEG_QUALITY = 85  # a background for the path, not a measurement: ~10× smaller than PNG


@dataclass(frozen=True, slots=True)
class Frame:
    """One kept frame: BGR, undistorted, as the operation measured on it."""

    image: np.ndarray
    taken_at: float  # Unix time the camera delivered it
    source: str  # the operation that captured it (trajectory, create_workpiece, ...)
    run_id: str  # that operation's run
    seq: int  # rises by one per frame kept since the server started

    @property
    def width(self) -> int:
        return int(self.image.shape[1])

    @property
    def height(self) -> int:
        return int(self.image.shape[0])


class LatestFrame:
    """Holds the newest frame; `keep` on the event loop, `jpeg` from any thread."""

    def __init__(self) -> None:
        self._frame: Frame | None = None
        self._seq = itertools.count(1)
        self._lock = threading.Lock()  # one encoding per frame, however many readers
        self._jpeg: tuple[int, bytes] | None = None

    @property
    def latest(self) -> Frame | None:
        return self._frame

    def keep(
        self, image: np.ndarray, *, source: str, run_id: str = "", taken_at: float | None = None
    ) -> Frame:
        """Make `image` the latest frame (replacing the one before) and return its record."""
        frame = Frame(
            image=image,
            taken_at=time.time() if taken_at is None else taken_at,
            source=source,
            run_id=run_id,
            seq=next(self._seq),
        )
        self._frame = frame
        return frame

    def jpeg(self, frame: Frame) -> bytes:
        """`frame` as JPEG (blocking: call it in a worker thread); cached for the newest frame."""
        with self._lock:
            cached = self._jpeg
            if cached is not None and cached[0] == frame.seq:
                return cached[1]
            ok, encoded = cv2.imencode(
                ".jpg", frame.image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]
            )
            if not ok:
                raise ValueError(f"the frame of {frame.source} could not be encoded as JPEG")
            data = encoded.tobytes()
            if self._frame is not None and self._frame.seq == frame.seq:
                self._jpeg = (frame.seq, data)
            return data
