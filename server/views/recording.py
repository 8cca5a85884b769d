"""The flight recorder: each run's device samples, journaled with the run.

Why from the live feed (server/views/live.py): it already reads the valve, flow,
pressure and the robot's pose every `device_push_interval` (0.1 s) while an
operation runs, and publishes them without waiting on anything. The recorder is
told of each `device` message the feed builds (`DeviceFeed.listeners`), keeps
the ones taken while a run is under way as rows of `run_samples`, and hands
them to the journal's writer `run_recording_flush_s` at a time, in one
transaction, not durable (`Journal.append` queues and returns: the feed, and so
the worker, never waits on the disk). A run's end, and a read of a recording
(`flush` before the journal is caught up), write what is left at once, so a
recording read after its run ended is complete.

The speed is the tool point's, between the last two poses the robot reported
(distance over the time between the reports): the controller does not report a
speed, and the commanded one says nothing of a stop or a slow start.

`run_samples` is a journal table like the others: pruned by retention, sealed by
the commit chain, and GET /runs/{run_id}/recording serves it (JSON or CSV).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol

from server.settings.recording import RecordingSettings
from server.storage.journal import Journal, records
from server.storage.journal.records import Record

SAME_REPORT_S = 0.001  # two pose times closer than this are one report, read twice


class _Runs(Protocol):
    def current_run(self) -> dict[str, Any] | None: ...


@dataclass(frozen=True, slots=True)
class _Pose:
    x: float
    y: float
    z: float
    at: float


def _taken(part: dict[str, Any], now: float) -> float | None:
    """When a device's reading in a `device` message was taken (Unix time), from its age."""
    age = part.get("age_ms")
    return None if age is None else now - float(age) / 1000.0


def sample_row(
    message: dict[str, Any], now: float, run_id: str, previous: _Pose | None
) -> tuple[dict[str, Any], _Pose | None]:
    """A `run_samples` row from a `device` message taken at `now`, and the pose it read.

    Pure, so the speed rule is tested without a feed. `previous` is the pose of the
    run's last sample: the speed is the distance from it over the time between the
    two reports; the same report twice keeps no speed (None) rather than a false 0.
    """
    glue, robot = message.get("glue", {}), message.get("robot", {})
    position = robot.get("position")
    pose = None
    if position is not None and len(position) >= 3:
        taken = _taken(robot, now)
        pose = _Pose(float(position[0]), float(position[1]), float(position[2]), taken or now)
    speed = None
    if pose is not None and previous is not None and not _same_report(pose, previous):
        distance = math.dist((pose.x, pose.y, pose.z), (previous.x, previous.y, previous.z))
        speed = distance / (pose.at - previous.at)
    row = {
        "time": now,
        "run_id": run_id,
        "x_mm": pose.x if pose else None,
        "y_mm": pose.y if pose else None,
        "z_mm": pose.z if pose else None,
        "pose_at": pose.at if pose else None,
        "speed_mm_s": speed,
        "valve_open": bool(glue.get("valve_open")),
        "flow_ml_min": glue.get("flow_ml_min"),
        "pressure_psi": glue.get("pressure_psi"),
        "glue_at": _taken(glue, now),
    }
    return row, pose


def _same_report(pose: _Pose, previous: _Pose) -> bool:
    """Whether `pose` is the report `previous` was, read again (the ages in a `device`
    message are rounded to 0.1 ms), or an older one: no new speed from it."""
    return pose.at <= previous.at + SAME_REPORT_S


class FlightRecorder:
    """Keeps the `device` messages taken during a run and journals them in batches.

    `sample` is called by the live feed with each message it publishes; it never
    blocks (appending to the journal queues the rows for its writer thread).
    """

    def __init__(self, settings: RecordingSettings, journal: Journal, runs: _Runs) -> None:
        self.settings = settings
        self.journal = journal
        self.runs = runs
        self._run_id: str | None = None
        self._pending: list[Record] = []
        self._first_at: float | None = None
        self._pose: _Pose | None = None
        self._speed: float | None = None

    def sample(self, message: dict[str, Any], now: float) -> None:
        """One `device` message the feed published at Unix time `now`."""
        if not self.settings.run_recording:
            return
        run = self.runs.current_run()
        run_id = None if run is None else str(run["run_id"])
        if run_id != self._run_id:
            self.flush()
            self._run_id, self._pose, self._speed = run_id, None, None
        if run_id is None:
            return
        row, pose = sample_row(message, now, run_id, self._pose)
        if pose is not None and self._pose is not None and _same_report(pose, self._pose):
            row["speed_mm_s"] = self._speed  # the same report: the speed last measured
        elif pose is not None:
            self._pose, self._speed = pose, row["speed_mm_s"]
        self._pending.append(records.run_sample(**row))
        if self._first_at is None:
            self._first_at = now
        if now - self._first_at >= self.settings.run_recording_flush_s:
            self.flush()

    def run_ended(self, run_id: str) -> None:
        """A run ended: what is left of its samples goes to the journal now."""
        if run_id == self._run_id:
            self.flush()

    def flush(self) -> None:
        """Hand the samples kept so far to the journal's writer, as one transaction."""
        if self._pending:
            self.journal.append(self._pending, durable=False)
        self._pending, self._first_at = [], None
