"""A run's hold on the devices, cut the moment the run is cancelled.

Why: a run ends by cancellation (cancel, e-stop, a fault, a timeout), and a
cancellation can be lost below the run: Python 3.11's asyncio.wait_for drops one
that lands as the awaited call ends (CPython gh-86296), and a library may do the
same. Such a run would go on after its stop and send its next move.
The worker gives up waiting for it after emergency_stop_timeout, so nothing would
stop it from moving the arm or opening the valve after the cell had stopped.

So each run gets its devices through a leash. Once the leash is cut (before the
cancellation is sent), whatever would move the arm or make glue flow is refused
at once with a CancelledError, which also restores the lost cancellation.
Stopping the arm, closing the valve and reading stay allowed: they are always safe.

What the run asked for before the cut is not taken back at the robot: a move is
written to its socket in the call's first step, so it is on the wire before any
stop made after the cut. The dispenser's line is different: an opening may wait
there behind another exchange, and a close goes ahead of it. So cutting the leash
also refuses the openings still waiting (`drop_waiting_openings`); otherwise one
would go out after the halt's close and open the valve again.

So the halt that follows the cut sends the last valve command of the run's
time. The run's own close as it ends (its `finally`) waits for that halt instead
of queueing another close behind it: once the halt has read the valve back
closed, the run's close is answered without an exchange on the line, where it
would cost the stop's answer two exchanges (a few tenths of a ms, milliseconds
when the dispenser is slow to answer). When the halt could not confirm the
close, or no halt follows the cut (at shutdown), the run's close is sent.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any, cast

from server.drivers.base import GlueDispenser, Pose, Robot

log = logging.getLogger(__name__)


class Leash:
    """Whether the run holding it may still command motion and glue."""

    def __init__(self, run_id: str, glue: GlueDispenser) -> None:
        self.run_id = run_id
        self.cut = False
        self._glue = glue
        # The halt after the cut: did it read the valve back closed? (None: no halt follows)
        self._halt: asyncio.Future[bool] | None = None

    def cut_now(self, *, halt_follows: bool) -> None:
        """No motion and no glue from now on, an opening waiting for the line included.

        `halt_follows`: the cell's halt is made next, and reports to `halted`.
        """
        if not self.cut and halt_follows:
            self._halt = asyncio.get_running_loop().create_future()
        self.cut = True
        dropped = self._glue.drop_waiting_openings()
        if dropped:
            log.warning("run %s was cancelled: its valve opening waiting refused", self.run_id)

    def halted(self, valve_closed: bool) -> None:
        """The halt after the cut has ended; `valve_closed`: it read the valve back closed."""
        if self._halt is not None and not self._halt.done():
            self._halt.set_result(valve_closed)

    async def closed_by_halt(self) -> bool:
        """Whether the halt after the cut read the valve back closed (waits for it to end)."""
        if self._halt is None:
            return False
        return await asyncio.shield(self._halt)

    def check(self, what: str) -> None:
        """Raise CancelledError when the run was cancelled: `what` is refused."""
        if self.cut:
            log.warning("run %s was cancelled: %s refused", self.run_id, what)
            raise asyncio.CancelledError(f"run {self.run_id} was cancelled: {what} refused")


class _LeashedRobot:
    def __init__(self, robot: Robot, leash: Leash) -> None:
        self._robot = robot
        self._leash = leash

    async def move_linear(self, pose: Pose, speed: float, acceleration: float) -> None:
        self._leash.check("a linear move")
        await self._robot.move_linear(pose, speed, acceleration)

    async def move_joint(self, target: Pose, speed: float) -> None:
        self._leash.check("a joint move")
        await self._robot.move_joint(target, speed)

    def __getattr__(self, name: str) -> Any:  # reads, stop, health: as the robot's own
        return getattr(self._robot, name)


class _LeashedGlue:
    def __init__(self, glue: GlueDispenser, leash: Leash) -> None:
        self._glue = glue
        self._leash = leash

    async def set_valve(self, open_: bool) -> None:
        if open_:
            self._leash.check("opening the valve")
        elif self._leash.cut and await self._leash.closed_by_halt():
            return  # closed by the halt, after the run's last opening (see the module doc)
        await self._glue.set_valve(open_)

    def __getattr__(self, name: str) -> Any:  # setpoints, reads, health: the dispenser's
        return getattr(self._glue, name)


def leashed(robot: Robot, glue: GlueDispenser, leash: Leash) -> tuple[Robot, GlueDispenser]:
    """The robot and the dispenser as a run sees them: held by `leash`."""
    return cast(Robot, _LeashedRobot(robot, leash)), cast(GlueDispenser, _LeashedGlue(glue, leash))
