"""When a robot move should end, and when to ask the controller whether it has.

The controller is polled (`isMoving`): nothing tells the client a move has ended.
The arm stands still at each waypoint until the client sees it has arrived, valve
open while spraying, so a poll that comes late is glue on the part: on a circle of
thirty-odd segments, half a poll interval at each was a tenth more glue than its
path needs (tests/integration/test_defects_caught.py).
"""

from __future__ import annotations

import math

from server.drivers.base import Pose

FINE_POLL_SHARE = 0.2  # the poll interval's share just after a move's expected end


def expected_move_duration(start: Pose, target: Pose, speed: float) -> float:
    """Seconds a move should take: the larger of the tool-point distance (mm) and the
    largest orientation change (deg) over speed, ignoring acceleration.

    Only an estimate: the move's deadline adds the full timeout to it, and the
    polls are placed by it; the simulator times its moves by the same rule.
    """
    distance = math.dist(start[:3], target[:3])
    turn = max(abs(b - a) for a, b in zip(start[3:], target[3:], strict=True))
    return max(distance, turn) / speed


def next_poll_s(until_expected_end: float, interval: float) -> float:
    """Seconds to the next isMoving: every `interval`, but at the move's expected end
    when that comes sooner, and finely (FINE_POLL_SHARE of it) for the interval after
    the end: an arm that accelerates arrives a little late."""
    if until_expected_end > interval:
        return interval
    if until_expected_end > 0:
        return until_expected_end
    if until_expected_end > -interval:
        return interval * FINE_POLL_SHARE
    return interval
