"""The run's sampler: the robot's position and the dispenser's flow while the path runs.

Why it cannot delay a move or a stop:

- the robot's link is pipelined (server/drivers/robot_jsonrpc.py): a
  `getPosition` holds no lock, and `stop()` is written at once whatever is
  pending. The sampler asks only while a spray segment is drawn, one request
  at a time, and waits at most one interval for the answer; a pose another
  reader took within the interval (a move's own, the live feed's) is used
  instead of asking again, and the sampler's reads refresh the driver's pose
  for the live feed the same way;
- the dispenser's line is shared, and a valve close waits for the exchange on
  the wire: so the sampler adds no Modbus exchange at all. It takes the
  readings the driver's monitor already polls every glue_poll_interval
  (`health.details`, `status_at`), each once. Flow resolution is therefore
  the monitor's interval (0.1 s by default). The glue dispensed is the
  dispenser's own totaliser in those readings, so after the path the run waits
  for one more poll (`closed_reading`): the first to show the valve closed,
  whose count holds the last drop.

The trajectory operation tells it which segment the robot draws
(`drawing`) and when the valve's open and close were answered (`opened`,
`closed`): the sampler needs no knowledge of the plan.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from typing import Any

from server.drivers.base import GlueDispenser, Robot
from server.quality.model import FlowSample, PoseSample, RunSamples, SprayWindow

log = logging.getLogger(__name__)

CLOSED_READING_POLL_S = 0.01  # how often `closed_reading` looks for the monitor's next poll


class RunSampler:
    """Collects `RunSamples` every `interval` s between start() and stop()."""

    def __init__(self, robot: Robot, glue: GlueDispenser, interval: float) -> None:
        self.robot = robot
        self.glue = glue
        self.interval = interval
        self.samples = RunSamples()
        self._segment: int | None = None
        self._task: asyncio.Task[None] | None = None
        self._last_status_at: float | None = None
        self._last_pose_at: float | None = None

    # --- what the operation tells ------------------------------------------------

    def drawing(self, segment: int | None) -> None:
        """The robot now draws `segment` (1-based), or travels (None)."""
        self._segment = segment

    def opened(self, segment: int) -> None:
        self.samples.windows.append(SprayWindow(segment, time.monotonic()))

    def closed(self) -> None:
        windows = self.samples.windows
        if windows and windows[-1].closed_at is None:
            windows[-1].closed_at = time.monotonic()

    # --- the task --------------------------------------------------------------------

    def start(self) -> None:
        if self._task is None:
            self._task = asyncio.create_task(self._run(), name="quality-sampler")

    async def stop(self) -> RunSamples:
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._take_flow()
        self.closed()
        return self.samples

    async def _run(self) -> None:
        while True:
            started = time.monotonic()
            self._take_flow()
            segment = self._segment
            if segment is not None:
                await self._take_pose(segment)
            await asyncio.sleep(max(0.0, self.interval - (time.monotonic() - started)))

    def _take_flow(self) -> None:
        details = self.glue.health.details
        taken = details.get("status_at")
        if taken is None or taken == self._last_status_at:
            return
        self._last_status_at = taken
        # status_at is wall time; the samples are on the monotonic clock of the windows.
        at = time.monotonic() - max(0.0, time.time() - float(taken))
        self.samples.flows.append(
            FlowSample(
                at,
                float(details.get("flow_ml_min") or 0.0),
                float(details.get("flow_setpoint_ml_min") or 0.0),
                bool(details.get("valve_open")),
                self._total_of(details, taken),
            )
        )

    @staticmethod
    def _total_of(details: dict[str, Any], taken: float) -> float | None:
        """The totaliser's count if the reading at `taken` carried it (a valve's read-back
        updates the valve and `status_at` alone)."""
        total = details.get("dispensed_ml")
        if total is None or details.get("dispensed_at") != taken:
            return None
        return float(total)

    async def closed_reading(self, within: float) -> bool:
        """Wait up to `within` s for a status reading taken after the valve's last close
        that shows it closed (quality/dispensing.py counts the glue up to it); whether one
        came. No wait for a dispenser whose readings carry no count."""
        windows = self.samples.windows
        if not windows or windows[-1].closed_at is None:
            return False
        if all(f.total_ml is None for f in self.samples.flows):
            return False
        closed_at = windows[-1].closed_at
        deadline = time.monotonic() + within
        while True:
            self._take_flow()
            last = self.samples.flows[-1] if self.samples.flows else None
            if last and last.at >= closed_at and not last.valve_open and last.total_ml is not None:
                return True
            if time.monotonic() >= deadline:
                return False
            await asyncio.sleep(CLOSED_READING_POLL_S)

    async def _take_pose(self, segment: int) -> None:
        details = self.robot.health.details
        taken = details.get("position_at")
        fresh = taken is not None and time.time() - float(taken) < self.interval
        if not fresh:
            try:
                async with asyncio.timeout(self.interval):
                    await self.robot.get_position()
            except Exception:  # a read lost is a sample lost; the driver reports faults
                return
            taken = details.get("position_at")
        if taken is None or taken == self._last_pose_at or self._segment != segment:
            return
        self._last_pose_at = taken
        position: list[float] = list(details.get("position") or [])
        if len(position) < 2:
            return
        at = time.monotonic() - max(0.0, time.time() - float(taken))
        self.samples.poses.append(PoseSample(at, float(position[0]), float(position[1]), segment))
