"""The camera's set-up view: a live, annotated picture of the table while someone watches.

Before calibrating, a technician places the markers, focuses the lens and lights the
table; this is what they look at (the dashboard's Set-up page, /camera/preview/ws). Each
frame is undistorted when the camera is calibrated, then shows the ArUco markers found
(outlined and numbered by the calibration's own detector), the workspace through the
robot calibration's map, and the focus and exposure figures (server/vision/setup_figures.py),
which also go to the client as JSON with the frame.

Why it cannot get in the way of the cell:

- one producer for every watcher: one capture, one detection, one JPEG per frame,
  whatever the number of clients (at most camera_preview_clients), at most
  camera_preview_fps frames a second;
- it runs only while someone watches: the first watcher starts it, the last one leaving
  ends it (no capture at all otherwise);
- the capture is the driver's (off the loop, bounded by its timeout); undistortion,
  detection, drawing and encoding run on one thread of their own, never on the loop and
  never on the shared pool the journal and the drivers use;
- each watcher holds only the newest frame: a slow client skips frames, nothing queues;
- it runs in IDLE only (`ALLOWED`): in every other state an operation may need the camera
  (calibrations, workpiece creation, a run's contour matching), a reset's probe captures
  a frame, or the cell is not up. Asked elsewhere it is refused; when the cell leaves IDLE
  every watcher is ended with the reason before another frame is captured. A frame being
  captured at that moment is dropped; a real camera's capture thread then serves the
  operation's frame right after it (one frame period at most).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import time
from dataclasses import dataclass, field
from typing import Any, Protocol

import cv2
import numpy as np

from server.common.errors import DeviceError
from server.core.machine.transitions import State
from server.core.operations.camera_frames import robot_calibration_problem
from server.core.worker.view import CellView
from server.drivers.base import Camera
from server.security.tokens import Principal
from server.settings.model import Settings
from server.storage import CellStores
from server.vision.markers import MarkerDetector, missing_markers
from server.vision.setup_figures import measure
from server.vision.setup_overlay import draw_setup_view, workspace_outline_mm

log = logging.getLogger(__name__)

ALLOWED = frozenset({State.IDLE})
STREAM_WIDTH = 960  # px sent: half of the 1920 camera, enough to see each marker's outline
JPEG_QUALITY = 80

# Why a watcher's stream ended: a WebSocket close code and the reason.
CLOSE_CAMERA_BUSY = 4409
CLOSE_CAMERA_FAILED = 1011
CLOSE_UNAUTHORIZED = 4401


class PreviewCell(Protocol):
    """What the preview reads of the cell (server.bootstrap.cell.Cell is one)."""

    @property
    def started(self) -> bool: ...
    @property
    def view(self) -> CellView: ...
    @property
    def devices(self) -> Any: ...  # CellDevices: its `camera`

    stores: CellStores | None


class PreviewRefused(Exception):
    """The stream cannot open now: an HTTP status and why (what the handshake answers)."""

    def __init__(self, status: int, reason: str) -> None:
        super().__init__(reason)
        self.status = status
        self.reason = reason


@dataclass(frozen=True, slots=True)
class PreviewFrame:
    """One annotated frame and its figures, shared by every watcher."""

    seq: int
    jpeg: bytes
    figures: dict[str, Any]


@dataclass(eq=False, slots=True)
class Watcher:
    """One client of the stream: the newest frame not yet sent, and how it ends."""

    principal: Principal
    ended: asyncio.Future[tuple[int, str]] = field(
        default_factory=lambda: asyncio.get_running_loop().create_future()
    )
    _frame: PreviewFrame | None = None
    _fresh: asyncio.Event = field(default_factory=asyncio.Event)

    def offer(self, frame: PreviewFrame) -> None:
        """Replace the frame waiting to be sent (a slow client skips frames, never queues)."""
        self._frame = frame
        self._fresh.set()

    async def next_frame(self) -> PreviewFrame:
        await self._fresh.wait()
        self._fresh.clear()
        assert self._frame is not None
        return self._frame

    def end(self, code: int, reason: str) -> None:
        if not self.ended.done():
            self.ended.set_result((code, reason))


class CameraPreview:
    """The set-up view's one producer and its watchers."""

    def __init__(self, cell: PreviewCell, settings: Settings) -> None:
        self._cell = cell
        self._settings = settings
        self._watchers: set[Watcher] = set()
        self._task: asyncio.Task[None] | None = None
        self._detector = MarkerDetector()
        self._seq = 0
        self.last_figures: dict[str, Any] | None = None

    @property
    def clients(self) -> int:
        return len(self._watchers)

    @property
    def running(self) -> bool:
        return self._task is not None and not self._task.done()

    def state_refusal(self) -> str | None:
        """Why the camera may not be streamed in the cell's present state (None: it may)."""
        if not self._cell.started:
            return "the cell is starting: the set-up view opens in IDLE"
        state = self._cell.view.state
        if state in ALLOWED:
            return None
        return (
            f"the cell is {state.value}: the set-up view runs in IDLE only, where no "
            "operation or reset needs the camera"
        )

    def refusal(self) -> PreviewRefused | None:
        """Why one more watcher may not open the stream now (None: it may)."""
        if (why := self.state_refusal()) is not None:
            return PreviewRefused(409, why)
        limit = self._settings.camera_preview_clients
        if len(self._watchers) >= limit:
            return PreviewRefused(
                503, f"the set-up view has {limit} clients already (camera_preview_clients)"
            )
        return None

    def watch(self, principal: Principal) -> Watcher:
        """Open a stream (raises PreviewRefused); the producer starts with the first."""
        if (refused := self.refusal()) is not None:
            raise refused
        watcher = Watcher(principal)
        self._watchers.add(watcher)
        if not self.running:
            self._task = asyncio.create_task(self._produce(), name="camera-preview")
        return watcher

    def leave(self, watcher: Watcher) -> None:
        """The watcher is gone; the producer stops after its frame in hand if none is left."""
        self._watchers.discard(watcher)

    def revoke(self, token_id: str) -> None:
        """End the streams of a revoked token."""
        for watcher in [w for w in self._watchers if w.principal.token_id == token_id]:
            watcher.end(CLOSE_UNAUTHORIZED, "unauthorized: the token was revoked")

    async def close(self) -> None:
        """End every stream and the producer (the server is stopping)."""
        self._end_all(1012, "the server is stopping")
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    # --- the producer ------------------------------------------------------------------------

    def _end_all(self, code: int, reason: str) -> None:
        for watcher in list(self._watchers):
            watcher.end(code, reason)
        self._watchers.clear()

    async def _produce(self) -> None:
        loop = asyncio.get_running_loop()
        # One thread of its own: a frame's processing never takes a thread the journal or a
        # driver is waiting for, and frames are processed one at a time.
        executor = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="camera-preview")
        try:
            while self._watchers:
                started = loop.time()
                if (why := self.state_refusal()) is not None:
                    self._end_all(CLOSE_CAMERA_BUSY, why)
                    return
                camera: Camera = self._cell.devices.camera
                try:
                    raw = await camera.capture()
                    taken_at = time.time()
                except DeviceError as exc:
                    self._end_all(CLOSE_CAMERA_FAILED, f"camera: {exc}"[:120])
                    return
                if (why := self.state_refusal()) is not None:  # it changed while capturing
                    self._end_all(CLOSE_CAMERA_BUSY, why)
                    return
                job = self._job(raw, taken_at)
                frame = await loop.run_in_executor(executor, job)
                self.last_figures = frame.figures
                for watcher in self._watchers:
                    watcher.offer(frame)
                period = 1.0 / self._settings.camera_preview_fps
                await asyncio.sleep(max(0.0, started + period - loop.time()))
        except Exception:  # a bug here must end the streams, not leave them waiting
            log.exception("the camera set-up view failed")
            self._end_all(CLOSE_CAMERA_FAILED, "the set-up view failed: see the server log")
        finally:
            executor.shutdown(wait=False)

    def _job(self, raw: np.ndarray, taken_at: float) -> Any:
        """What to run off the loop for one frame, with the calibration read now, on the loop."""
        stores = self._cell.stores
        assert stores is not None
        calibration = stores.calibration
        undistort = calibration.undistort
        undistorted = calibration.camera is not None
        problem = robot_calibration_problem(calibration, "the workspace outline")
        robot_map = calibration.robot if problem is None else None
        settings = self._settings
        expected = range(len(settings.marker_positions_mm))
        self._seq += 1
        seq = self._seq

        def process() -> PreviewFrame:
            image = undistort(raw)
            detections = self._detector.detect(image, expected=expected)
            figures = measure(image)
            workspace_px = None
            if robot_map is not None:
                outline = workspace_outline_mm(settings.workspace_min_mm, settings.workspace_max_mm)
                workspace_px = robot_map.to_pixels(outline)
            found = sorted(i for i in detections if i in expected)
            missing = missing_markers(detections, expected)
            workspace_note = (
                None
                if robot_map is not None
                else "workspace not drawn: no robot calibration matching the camera's"
            )
            lines = [
                f"markers {len(found)} of {len(expected)}"
                + (f"  missing {', '.join(map(str, missing))}" if missing else ""),
                f"sharpness {figures.sharpness:.0f}  brightness {figures.brightness:.0f}/255",
                f"clipped {figures.over_exposed_pct:.1f}% white  "
                f"{figures.under_exposed_pct:.1f}% black",
            ]
            if workspace_note:
                lines.append(workspace_note)
            picture = draw_setup_view(image, detections, workspace_px, lines, width=STREAM_WIDTH)
            ok, encoded = cv2.imencode(".jpg", picture, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
            if not ok:
                raise RuntimeError("JPEG encoding of the set-up view failed")
            height, width = image.shape[:2]
            return PreviewFrame(
                seq,
                encoded.tobytes(),
                {
                    "type": "frame",
                    "seq": seq,
                    "taken_at": round(taken_at, 3),
                    "camera_size": [width, height],
                    "image_size": [picture.shape[1], picture.shape[0]],
                    "undistorted": undistorted,
                    "sharpness": figures.sharpness,
                    "brightness": figures.brightness,
                    "over_exposed_pct": figures.over_exposed_pct,
                    "under_exposed_pct": figures.under_exposed_pct,
                    "markers_found": len(found),
                    "markers_expected": len(expected),
                    "markers": found,
                    "missing": missing,
                    "workspace_drawn": robot_map is not None,
                    "workspace_note": workspace_note,
                },
            )

        return process
