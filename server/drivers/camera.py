"""The cell camera: a real camera through OpenCV, and a simulated one with exact ground truth.

Both implement `server.drivers.base.Camera` and behave the same towards the core:

- the event loop never blocks: OpenCV calls and rendering run in worker threads;
- every frame is bounded by `timeout` (the cell's vision_processing_timeout) and a camera that
  does not deliver in time gives `DeviceTimeout`; a camera that is gone gives
  `DeviceDisconnected`; other failures `DeviceError`. Messages say what to check;
- a failed capture also goes to the fault listener, once per outage (the next good frame
  re-arms it), so the machine can go to ERROR without a flood of repeats;
- `health` shows connected, the capture time of the last frame (rtt), the last error, and
  the resolution in `details`.

`OpenCVCamera` keeps its `cv2.VideoCapture` on one dedicated daemon thread rather than
`asyncio.to_thread`: a VideoCapture is not thread-safe, so after a timed-out read the next call
must queue behind the stuck one instead of running beside it on another pool thread; a stuck
driver call then ties up only that thread (not the shared pool the other drivers use), and,
being a daemon, it cannot keep the server from exiting.

`SimulatedCamera` renders the table or a cycle of chessboard views (see
`server.drivers.sim.camera_scene`) in the image process (`server.vision.process`), as a
camera of its own would, and takes injected faults.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import math
import os
import queue
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any, Literal, TypeVar

import cv2
import numpy as np

from server.common.errors import DeviceDisconnected, DeviceError, DeviceTimeout
from server.drivers import wear
from server.drivers.base import DeviceFault, DeviceHealth, FaultListener
from server.drivers.sim.camera_bead import BeadSource, Shift
from server.drivers.sim.camera_model import shifted_camera
from server.drivers.sim.camera_scene import (
    DEFAULT_CAMERA_MODEL,
    DEFAULT_CHESSBOARD,
    BoardPose,
    CameraModel,
    Chessboard,
    Scene,
    Workpiece,
    default_chessboard_poses,
    draw_table_ahead,
    release_chessboard_state,
    render_chessboard_view,
    render_table,
)
from server.vision.process import IMAGE_PROCESS

logger = logging.getLogger(__name__)

DEVICE = "camera"
T = TypeVar("T")

# The simulator builds its per-pixel maps and its table (~2 s) for the first frame, in the
# image process, which itself takes a second to start: connect() and the first capture allow
# this much for that one-off warm-up, so a short capture timeout does not fail either.
SIM_WARM_UP_S = 30.0


class _CameraBase:
    """Health and once-per-outage fault reporting, shared by the real and simulated camera."""

    def __init__(self, timeout: float) -> None:
        if timeout <= 0:
            raise ValueError(f"camera timeout must be positive, got {timeout}")
        self.timeout = float(timeout)
        self.health = DeviceHealth(DEVICE)
        self._listener: FaultListener | None = None
        self._outage = False

    def set_fault_listener(self, listener: FaultListener | None) -> None:
        """Where to report capture failures (once per outage)."""
        self._listener = listener

    def _frame_ok(self, started: float) -> None:
        self.health.record_ok(time.monotonic() - started)
        wear.add(self.health.details, wear.FRAMES, 1)
        if self._outage:
            self._outage = False
            logger.info("camera delivers frames again")

    def _frame_failed(self, code: str, message: str, *, connected: bool | None) -> None:
        self.health.record_error(message, connected=connected)
        if self._outage:
            return
        self._outage = True
        logger.warning("camera: %s", message)
        listener = self._listener
        if listener is None:
            return
        try:
            listener(DeviceFault(DEVICE, code, message))
        except Exception:  # a broken listener must not break the driver
            logger.exception("the camera fault listener failed on %s", code)


# --- the real camera ---------------------------------------------------------------------------


class _CaptureThread:
    """One daemon thread that owns a VideoCapture and runs its calls one after another."""

    def __init__(self, name: str) -> None:
        self._jobs: queue.SimpleQueue[tuple[Callable[[], Any], concurrent.futures.Future] | None]
        self._jobs = queue.SimpleQueue()
        threading.Thread(target=self._run, name=name, daemon=True).start()

    def _run(self) -> None:
        while (job := self._jobs.get()) is not None:
            self._do(*job)
            # Not held while the thread waits for the next call: its future holds the
            # frame it read (6 MB at 1920x1080) until the next capture otherwise.
            del job

    @staticmethod
    def _do(call: Callable[[], Any], future: concurrent.futures.Future) -> None:
        if not future.set_running_or_notify_cancel():
            return  # the caller gave up before it started
        try:
            future.set_result(call())
        except BaseException as exc:
            future.set_exception(exc)

    def submit(self, call: Callable[[], T]) -> asyncio.Future[T]:
        future: concurrent.futures.Future[T] = concurrent.futures.Future()
        self._jobs.put((call, future))
        return asyncio.wrap_future(future)

    def stop(self) -> None:
        """Let the thread end once the calls already queued are done."""
        self._jobs.put(None)


class OpenCVCamera(_CameraBase):
    """A USB/V4L2 (or any cv2.VideoCapture) camera looking down on the table.

    The cell's vision is specified at 1920×1080. A camera that delivers less raises
    DeviceError in connect(): a lower resolution silently degrades every measurement, and a
    USB 2 port or hub is the usual cause. `allow_lower_resolution=True` (bench tests with a
    webcam) only logs a warning and puts it in `health.details["resolution_warning"]`.
    """

    def __init__(
        self,
        camera_id: int | str,
        *,
        timeout: float,
        width: int = 1920,
        height: int = 1080,
        allow_lower_resolution: bool = False,
    ) -> None:
        super().__init__(timeout)
        self.camera_id = camera_id
        # "0" from the environment means device index 0; anything else is a path or URL
        self._source: int | str = (
            int(camera_id) if isinstance(camera_id, str) and camera_id.isdigit() else camera_id
        )
        self.width, self.height = int(width), int(height)
        self.allow_lower_resolution = allow_lower_resolution
        self._cap: cv2.VideoCapture | None = None
        self._thread: _CaptureThread | None = None
        self.health.details.update(camera_id=str(camera_id), requested=f"{width}x{height}")

    def _open_blocking(self, abandoned: threading.Event) -> tuple[cv2.VideoCapture, np.ndarray]:
        """Open, ask for the resolution, and read one frame (runs on the capture thread)."""
        cap = cv2.VideoCapture(self._source)
        try:
            if not cap.isOpened():
                raise DeviceDisconnected(
                    DEVICE,
                    f"camera {self.camera_id} could not be opened: check the USB cable and "
                    "that no other program holds it",
                )
            # MJPG first: most UVC cameras give 1080p at full rate only in MJPG over USB.
            cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc(*"MJPG"))
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
            cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # keep at most one stale frame queued
            ok, frame = cap.read()
            if not ok or frame is None:
                raise DeviceDisconnected(
                    DEVICE,
                    f"camera {self.camera_id} opened but delivered no frame: check the cable, "
                    "the camera's power and that no other program holds it",
                )
        except BaseException:
            cap.release()
            raise
        if abandoned.is_set():  # connect() timed out meanwhile: nobody will use it
            cap.release()
        return cap, frame

    def _read_fresh(self) -> tuple[bool, np.ndarray | None]:
        """Drop the frame the driver may hold from before (the robot may have moved since)."""
        cap = self._cap
        if cap is None:
            return False, None
        cap.grab()
        return cap.read()

    async def connect(self) -> None:
        """Open the camera and read a first frame; DeviceError if it cannot deliver one."""
        if self._cap is not None:
            return
        thread = _CaptureThread(f"camera-{self.camera_id}")
        abandoned = threading.Event()
        started = time.monotonic()
        try:
            async with asyncio.timeout(self.timeout):
                cap, frame = await thread.submit(lambda: self._open_blocking(abandoned))
        except TimeoutError:
            abandoned.set()
            thread.stop()
            message = (
                f"camera {self.camera_id} did not open within {self.timeout:g} s: check the "
                "USB cable and that no other program holds it"
            )
            self.health.record_error(message, connected=False)
            raise DeviceTimeout(DEVICE, message) from None
        except DeviceError as exc:
            thread.stop()
            self.health.record_error(str(exc), connected=False)
            raise
        height, width = frame.shape[:2]
        self.health.details.update(resolution=f"{width}x{height}", backend=cap.getBackendName())
        if width < self.width or height < self.height:
            message = (
                f"camera {self.camera_id} delivers {width}x{height}, the cell needs "
                f"{self.width}x{self.height}: check the camera model and that it is on a USB 3 "
                "port without a hub"
            )
            if not self.allow_lower_resolution:
                thread.submit(cap.release)
                thread.stop()
                self.health.record_error(message, connected=False)
                raise DeviceError(DEVICE, message)
            logger.warning("%s (continuing: allow_lower_resolution is set)", message)
            self.health.details["resolution_warning"] = message
        self._cap, self._thread = cap, thread
        self._outage = False
        self._frame_ok(started)
        logger.info("camera %s open at %dx%d", self.camera_id, width, height)

    async def capture(self) -> np.ndarray:
        """One fresh BGR frame, within `timeout`."""
        if self._thread is None:
            raise DeviceDisconnected(DEVICE, f"camera {self.camera_id} is not open: connect first")
        started = time.monotonic()
        try:
            async with asyncio.timeout(self.timeout):
                ok, frame = await self._thread.submit(self._read_fresh)
        except TimeoutError:
            message = (
                f"camera {self.camera_id} delivered no frame within {self.timeout:g} s: check "
                "the USB cable; reconnect the camera if it persists"
            )
            self._frame_failed("NO_REPLY", message, connected=False)
            raise DeviceTimeout(DEVICE, message) from None
        if not ok or frame is None:
            message = (
                f"camera {self.camera_id} stopped delivering frames: check the USB cable and "
                "the camera's power, then reconnect"
            )
            self._frame_failed("COMM_LOST", message, connected=False)
            raise DeviceDisconnected(DEVICE, message)
        self._frame_ok(started)
        return frame

    async def close(self) -> None:
        """Release the camera; never raises, and waits at most a second for a stuck driver."""
        cap, thread = self._cap, self._thread
        self._cap = self._thread = None
        self.health.connected = False
        if thread is None or cap is None:
            return
        try:
            released = thread.submit(cap.release)
            thread.stop()
            # asyncio.wait does not cancel: a release queued behind a stuck read still runs
            await asyncio.wait({released}, timeout=min(1.0, self.timeout))
        except Exception:
            logger.exception("releasing camera %s failed", self.camera_id)


# --- the simulated camera ----------------------------------------------------------------------

FaultKind = Literal["fail", "stall"]


class SimulatedCamera(_CameraBase):
    """The cell camera in simulation: renders the table, or chessboard views, with ground truth.

    `scene` (markers, workpieces, lighting) and `model` (the exact camera) are public so tests
    can compare what vision measures with what is really there. In chessboard mode each
    capture shows the next of `chessboard_poses` (cycling), so an intrinsic calibration that
    captures N frames sees N different poses; `last_chessboard_pose` is the one just shown.
    """

    def __init__(
        self,
        scene: Scene | None = None,
        model: CameraModel | None = None,
        *,
        seed: int = 0,
        timeout: float = 5.0,
    ) -> None:
        super().__init__(timeout)
        self.scene = scene if scene is not None else Scene()
        self.model = model if model is not None else DEFAULT_CAMERA_MODEL
        self._rng = np.random.default_rng(seed)
        self._mode: Literal["table", "chessboard"] = "table"
        self.chessboard: Chessboard = DEFAULT_CHESSBOARD
        self.chessboard_poses: tuple[BoardPose, ...] = ()
        self._next_view = 0
        self.last_chessboard_pose: BoardPose | None = None
        self._fault: FaultKind | None = None
        self._stall_released: asyncio.Event | None = None
        self._open = False
        # The bead dispensed on the table (camera_bead.py): set where the simulators run in
        # the same process; None shows no bead.
        self.bead_source: BeadSource | None = None
        self._bead_since = -math.inf
        self._part_shifts: list[Shift] = []
        self._mounted_model = self.model
        self._first_frame: asyncio.Future[np.ndarray] | None = None  # drawn since connect
        self.health.details.update(
            simulated=True, resolution=f"{self.model.width}x{self.model.height}", mode=self._mode
        )

    # --- what the camera looks at --------------------------------------------------------

    @property
    def mode(self) -> Literal["table", "chessboard"]:
        return self._mode

    def show_table(self) -> None:
        """Look at the table: markers and workpieces (the default)."""
        self._mode = "table"
        self.health.details["mode"] = self._mode

    def show_chessboard(
        self, board: Chessboard | None = None, poses: Sequence[BoardPose] | None = None
    ) -> None:
        """Show a calibration board, a new pose per capture, starting from the first pose."""
        self.chessboard = board if board is not None else DEFAULT_CHESSBOARD
        self.chessboard_poses = (
            tuple(poses)
            if poses is not None
            else default_chessboard_poses(self.model, self.chessboard)
        )
        if not self.chessboard_poses:
            raise ValueError("show_chessboard needs at least one board pose")
        self._next_view = 0
        self.last_chessboard_pose = None
        self._mode = "chessboard"
        self.health.details["mode"] = self._mode

    def place_workpiece(
        self, name: str, x: float, y: float, rotation_deg: float = 0.0
    ) -> Workpiece:
        """Put a library workpiece (see WORKPIECE_SHAPES) on the table at x, y mm, rotated."""
        return self.scene.place_workpiece(name, x, y, rotation_deg)

    def clear_workpieces(self) -> None:
        """Take the parts off the table, and the glue on them with them."""
        self.scene.clear_workpieces()
        self.clear_bead()

    def clear_bead(self) -> None:
        """Forget the glue dispensed so far (the parts it was on have gone)."""
        self._bead_since = time.time()
        self._part_shifts.clear()

    def shift_part(self, dx_mm: float, dy_mm: float) -> None:
        """Fault: the parts slide by dx, dy mm now (after matching, e.g. while the run sprays);
        the glue already on them goes with them."""
        self.scene.shift_workpieces(dx_mm, dy_mm)
        self._part_shifts.append((time.time(), float(dx_mm), float(dy_mm)))

    def knock(self, dx_mm: float, dy_mm: float) -> None:
        """Fault: the camera knocked by dx, dy mm along the table from where it was mounted
        (0, 0 puts it back); markers, parts and table all appear displaced."""
        self.model = shifted_camera(self._mounted_model, dx_mm, dy_mm)

    def present_next_part(self) -> None:
        """The next part of a production order: the parts on the table replaced by fresh
        ones at the same poses (what a person or a conveyor does at a real cell), with no
        glue on them: the bead dispensed so far went with the old ones."""
        self.scene.present_next_part()
        self.clear_bead()

    # --- fault injection (tests) ---------------------------------------------------------

    def inject_fault(self, kind: FaultKind) -> None:
        """Make captures misbehave until clear_faults().

        "fail": each capture raises DeviceError (reported once per outage); "stall": captures
        hang, so the caller sees DeviceTimeout after `timeout`.
        """
        if kind not in ("fail", "stall"):
            raise ValueError(f"unknown camera fault {kind!r}: use 'fail' or 'stall'")
        if kind == "stall" and self._stall_released is None:
            self._stall_released = asyncio.Event()
        self._fault = kind

    def clear_faults(self) -> None:
        """Back to normal; a capture stalled right now goes on and delivers."""
        self._fault = None
        if self._stall_released is not None:
            self._stall_released.set()
            self._stall_released = None

    # --- Camera protocol -----------------------------------------------------------------

    async def connect(self) -> None:
        """Open: the image process that draws the frames answers; the first frame is drawn
        after, in the background (the render caches, see SIM_WARM_UP_S).

        Why not wait for that frame: it is the simulator's own set-up (a second or two of
        per-pixel maps), not the camera's link, and nothing needs a frame before a person
        commands an operation. Waited for here, it was most of a start-up's time to IDLE.
        The first capture waits for it (`warmed_up`, outside its own timeout), then draws
        from warm caches.
        """
        self._open = True
        started = time.monotonic()
        message = f"simulated camera did not open within {self.timeout:g} s (stall injected)"
        try:
            async with asyncio.timeout(self.timeout):
                await self._wait_out_faults()
            # Not a stall when it times out: the image process (a Python of its own) did
            # not start, which a machine short of CPU or memory shows first.
            waited = max(self.timeout, SIM_WARM_UP_S)
            message = f"the image process did not answer within {waited:g} s (host overloaded?)"
            async with asyncio.timeout(waited):
                await IMAGE_PROCESS.call(os.getpid)  # queued ahead of the first frame
            self._first_frame = asyncio.ensure_future(self._render(advance=False))
            self._first_frame.add_done_callback(_drawn_or_not)
        except TimeoutError:
            self._open = False
            self.health.record_error(message, connected=False)
            raise DeviceTimeout(DEVICE, message) from None
        except DeviceError as exc:
            self._open = False
            self.health.record_error(str(exc), connected=False)
            raise
        self._outage = False
        self._frame_ok(started)

    async def capture(self) -> np.ndarray:
        """One BGR frame (uint8, 1080×1920×3) of the table or of the next chessboard pose."""
        if not self._open:
            raise DeviceDisconnected(DEVICE, "simulated camera is not open: connect first")
        await self.warmed_up()
        started = time.monotonic()
        try:
            async with asyncio.timeout(self.timeout):
                await self._wait_out_faults(report=True)
                frame = await self._render(advance=True)
        except TimeoutError:
            message = (
                f"simulated camera delivered no frame within {self.timeout:g} s "
                "(stall injected): on a real cell, check the USB cable"
            )
            self._frame_failed("NO_REPLY", message, connected=False)
            raise DeviceTimeout(DEVICE, message) from None
        self._frame_ok(started)
        return frame

    async def warmed_up(self) -> None:
        """Wait (at most SIM_WARM_UP_S) for the first frame drawn since connect: its render
        caches, so that a capture timed by its caller is timed on its own frame.

        Callers that bound a capture by a timeout of their own (an operation's frame, the
        reset's probe) wait for this first, outside it. Never raises: a first frame that
        could not be drawn is the next capture's to report."""
        first, self._first_frame = self._first_frame, None
        if first is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(asyncio.shield(first), SIM_WARM_UP_S)

    async def close(self) -> None:
        """Close; never raises."""
        self._open = False
        self.health.connected = False
        first, self._first_frame = self._first_frame, None
        if first is not None:
            first.cancel()  # the image process finishes drawing it; nobody waits for it

    # --- internals -------------------------------------------------------------------------

    async def _wait_out_faults(self, *, report: bool = False) -> None:
        released = self._stall_released
        if self._fault == "stall" and released is not None:
            await released.wait()
        if self._fault == "fail":
            message = "simulated camera failure (injected): no frame delivered"
            if report:
                self._frame_failed("CAPTURE_FAILED", message, connected=None)
            raise DeviceError(DEVICE, message)

    async def draw_ahead(self) -> None:
        """Draw the table as it stands now, delivering nothing: the next capture of an
        unchanged table only adds the sensor's noise. Never raises.

        A real camera streams, so a frame asked for arrives within its frame period;
        this one draws each frame when asked (a remap of the whole table, more with a
        bead that changed). An operation that knows what the camera will see before it
        may look (the inspection, while the arm clears the part) calls this, so the
        simulator's drawing is not counted in the frame's wait. The frame still shows
        the table as it is at its capture: a table changed since is drawn again."""
        drawing_first = self._first_frame is not None  # the first frame builds the caches
        if not self._open or self._mode != "table" or self._fault is not None or drawing_first:
            return
        with contextlib.suppress(Exception):  # the capture draws, and reports, its own
            await IMAGE_PROCESS.call(draw_table_ahead, await self._table_scene(), self.model)

    async def _table_scene(self) -> Scene:
        """The table as it is now, with the bead dispensed on it."""
        scene = self.scene.snapshot()
        source = self.bead_source
        if source is not None:  # the in-process simulators' glue, gathered on a thread
            shifts = list(self._part_shifts)
            scene.bead = await asyncio.to_thread(source, self._bead_since, shifts)
        return scene

    async def _render(self, *, advance: bool) -> np.ndarray:
        """The next frame, rendered in the image process (`server.vision.process`): the
        simulator's work is a device's own, and would otherwise hold the server's
        interpreter lock for several ms at a time while it draws. What to draw is
        taken on the event loop, as it is now."""
        model = self.model
        rng = np.random.default_rng(int(self._rng.integers(0, 2**63 - 1)))
        draw: Callable[..., np.ndarray]
        args: tuple[Any, ...]
        if self._mode == "table":
            draw, args = _table_view, (await self._table_scene(), model, rng)
        else:
            board, pose = self.chessboard, self.chessboard_poses[self._next_view]
            if advance:
                self._next_view = (self._next_view + 1) % len(self.chessboard_poses)
                self.last_chessboard_pose = pose
            light = (self.scene.noise_sigma, self.scene.vignetting, self.scene.light_gradient)
            draw, args = _chessboard_view, (model, board, pose, rng, *light)
        shape = (model.height, model.width, 3)
        return await IMAGE_PROCESS.call(draw, *args, frame_out=(shape, np.uint8))


def _drawn_or_not(first: asyncio.Future[np.ndarray]) -> None:
    """The first frame's outcome is read, so a failure nobody awaited is not logged as lost
    (the next capture draws again and reports its own)."""
    if not first.cancelled():
        first.exception()


def _table_view(scene: Scene, model: CameraModel, rng: np.random.Generator) -> np.ndarray:
    """`render_table`, then what only chessboard views needed is let go (the image process
    keeps no calibration board's state while the camera looks at the table)."""
    frame = render_table(scene, model, rng)
    release_chessboard_state()
    return frame


def _chessboard_view(
    model: CameraModel,
    board: Chessboard,
    pose: BoardPose,
    rng: np.random.Generator,
    noise_sigma: float,
    vignetting: float,
    light_gradient: float,
) -> np.ndarray:
    """`render_chessboard_view` with its keywords given in order, as the image process calls it."""
    light = {"noise_sigma": noise_sigma, "vignetting": vignetting, "light_gradient": light_gradient}
    return render_chessboard_view(model, board, pose, rng=rng, **light)
