"""Where a run's end goes: the steps of the retract and the inspection, timed per run.

`StepClock` wraps, for the length of a benchmark, the functions that do each step
(module attributes and the image process's `call`, restored on exit), so the cell
runs its own code unchanged and the benchmark reads a timeline of each run's end:

- `retract: to clearance`: the retract's start → the arm clear of the camera's view
  (`inspection_clearance_mm`), when the inspection may take its frame;
- `retract: after clearance`: clearance → the arm at the safe position (what the
  inspection can overlap);
- `frame: bead gathered` / `frame: drawn`: the simulated camera's inspection frame (not
  the run's first frame, which finds the part), its bead from
  the simulators' records (a thread of the server) and its drawing (the image process);
  `frame: whole capture` is the camera's capture from request to frame;
- `frame: undistorted`: the frame undistorted (the image process);
- `analysis`: markers, parts, bead, verdict, annotation and JPEG (the image process);
- `image written`: the annotated JPEG to the data directory;
- `inspection: after clearance`: clearance (no retract: the last bead) → the
  inspection's result;
- `inspection: after the retract`: the part of that left once the arm is at the safe
  position (0 when the arm arrives last): what the inspection adds to the cycle;
- `run's end → IDLE`: the operation's result → the cell back in IDLE (the run's
  journal commit with its inspection row, the transition).
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Callable
from typing import Any

import server.core.operations.camera_frames as camera_frames
import server.core.operations.inspection as inspection
import server.core.operations.safe_position as safe_position
import server.core.operations.trajectory as trajectory
from server.drivers.camera import SimulatedCamera
from server.vision.process import IMAGE_PROCESS

STEP_ORDER = (
    "retract: to clearance",
    "retract: after clearance",
    "frame: bead gathered",
    "frame: drawn",
    "frame: whole capture",
    "frame: undistorted",
    "analysis",
    "image written",
    "inspection: after clearance",
    "inspection: after the retract",
    "run's end → IDLE",
)
IMAGE_STEPS = {"_table_view": "frame: drawn", "undistort_frame": "frame: undistorted"}
IMAGE_STEPS["look_at_part"] = "analysis"


class StepClock:
    """A timeline of each run's end (module docstring); `samples[mode][step]` in seconds."""

    def __init__(self, camera: object, images: object | None) -> None:
        self.samples: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
        self._marks: dict[str, float] = {}
        self._steps: dict[str, list[float]] = defaultdict(list)
        self._camera = camera
        self._images = images
        self._undo: list[Callable[[], None]] = []
        self._inspecting = False  # within the inspection's capture

    # --- a run ------------------------------------------------------------------------

    def begin_run(self) -> None:
        self._marks = {}
        self._steps = defaultdict(list)

    def end_run(self, idle_at: float, mode: str | None) -> None:
        """The run is back in IDLE: its steps' durations from its marks, kept under `mode`
        (None: a run not measured)."""
        marks, steps = self._marks, self._steps
        done = marks.get("result")
        if done is not None:
            steps["run's end → IDLE"].append(idle_at - done)
        cleared = marks.get("cleared", marks.get("path done"))
        inspected = marks.get("inspected")
        if cleared is not None and inspected is not None:
            steps["inspection: after clearance"].append(inspected - cleared)
        start, arrived = marks.get("retract"), marks.get("arrived")
        if start is not None and arrived is not None and "cleared" in marks:
            steps["retract: to clearance"].append(marks["cleared"] - start)
            steps["retract: after clearance"].append(arrived - marks["cleared"])
            if inspected is not None:
                steps["inspection: after the retract"].append(max(0.0, inspected - arrived))
        if mode is not None:
            for step, seconds in steps.items():
                self.samples[mode][step].extend(seconds)

    def _mark(self, name: str) -> None:
        self._marks.setdefault(name, time.perf_counter())

    def _add(self, step: str, seconds: float) -> None:
        if step.startswith("frame") and not self._inspecting:
            return  # the run's first frame (finding the part) is not the inspection's
        self._steps[step].append(seconds)

    # --- the wrapping -------------------------------------------------------------------

    def __enter__(self) -> StepClock:
        self._patch(trajectory, "retract_and_inspect", self._retract_and_inspect)
        self._patch(trajectory, "inspect_run", self._inspect_run)
        self._patch(safe_position, "move_to_safe_position", self._timed_move)
        self._patch(camera_frames, "capture", self._timed_capture)
        self._patch(inspection, "capture_undistorted", self._inspection_frame)
        self._patch_instance(IMAGE_PROCESS, "call", self._timed_image_call)
        if self._images is not None:
            self._patch_instance(self._images, "save", self._timed_save)
        if isinstance(self._camera, SimulatedCamera) and self._camera.bead_source is not None:
            self._camera.bead_source = self._timed_bead(self._camera.bead_source)
            source = self._camera

            def undo_bead(original: Any = self._camera.bead_source.__wrapped__) -> None:
                source.bead_source = original

            self._undo.append(undo_bead)
        return self

    def __exit__(self, *exc: object) -> None:
        for undo in reversed(self._undo):
            undo()
        self._undo.clear()

    def _patch(self, module: Any, name: str, make: Callable[[Any], Any]) -> None:
        original = getattr(module, name)
        setattr(module, name, make(original))
        self._undo.append(lambda: setattr(module, name, original))

    def _patch_instance(self, owner: Any, name: str, make: Callable[[Any], Any]) -> None:
        original = getattr(owner, name)
        setattr(owner, name, make(original))
        self._undo.append(lambda: delattr(owner, name))

    def _retract_and_inspect(self, original: Any) -> Any:
        async def wrapped(ctx: Any, beads: Any, inspect: Any) -> Any:
            self._mark("retract")
            if inspect is None:
                return await original(ctx, beads, None)

            def timed_inspect(cleared: Any) -> Any:
                async def seen_clear() -> object:
                    result = await cleared()
                    self._mark("cleared")
                    return result

                return inspect(seen_clear)

            return await original(ctx, beads, timed_inspect)

        return wrapped

    def _inspect_run(self, original: Any) -> Any:
        async def wrapped(ctx: Any, *args: Any) -> Any:
            if len(args) < 4 or args[3] is None:
                self._mark("path done")
            result = await original(ctx, *args)
            self._mark("inspected")
            return result

        return wrapped

    def _timed_move(self, original: Any) -> Any:
        async def wrapped(ctx: Any) -> Any:
            try:
                return await original(ctx)
            finally:
                self._mark("arrived")

        return wrapped

    def _timed_capture(self, original: Any) -> Any:
        async def wrapped(ctx: Any, purpose: str) -> Any:
            started = time.perf_counter()
            frame = await original(ctx, purpose)
            self._add("frame: whole capture", time.perf_counter() - started)
            return frame

        return wrapped

    def _inspection_frame(self, original: Any) -> Any:
        async def wrapped(ctx: Any, purpose: str) -> Any:
            self._inspecting = True
            try:
                return await original(ctx, purpose)
            finally:
                self._inspecting = False

        return wrapped

    def _timed_image_call(self, original: Any) -> Any:
        async def wrapped(fn: Any, *args: Any, **kwargs: Any) -> Any:
            started = time.perf_counter()
            result = await original(fn, *args, **kwargs)
            step = IMAGE_STEPS.get(getattr(fn, "__name__", ""))
            if step is not None:
                self._add(step, time.perf_counter() - started)
            return result

        return wrapped

    def _timed_save(self, original: Any) -> Any:
        def wrapped(run_id: str, jpeg: bytes) -> None:
            started = time.perf_counter()
            original(run_id, jpeg)
            self._add("image written", time.perf_counter() - started)
            self._mark("result")

        return wrapped

    def _timed_bead(self, original: Any) -> Any:
        def wrapped(*args: Any) -> Any:
            started = time.perf_counter()
            layer = original(*args)
            self._add("frame: bead gathered", time.perf_counter() - started)
            return layer

        wrapped.__wrapped__ = original  # type: ignore[attr-defined]
        return wrapped
