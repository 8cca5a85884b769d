"""The driver polls a move's end where it is due, not up to a poll interval after it.

The arm stands still at each waypoint until the driver sees it has arrived, with
the valve open while spraying: on a circle of thirty-odd segments, half a poll
interval at each was a tenth more glue than the path needs.
"""

from __future__ import annotations

import pytest

from server.drivers.robot_jsonrpc import JsonRpcRobot

pytestmark = pytest.mark.unit

INTERVAL = 0.01


def robot() -> JsonRpcRobot:
    return JsonRpcRobot("127.0.0.1", 1, poll_interval=INTERVAL)


def test_a_move_far_from_its_end_is_polled_every_interval() -> None:
    assert robot()._next_poll_s(1.0) == INTERVAL


def test_the_poll_due_after_the_expected_end_lands_on_it() -> None:
    assert robot()._next_poll_s(0.004) == pytest.approx(0.004)


def test_an_arm_a_little_late_is_polled_finely_then_at_the_interval_again() -> None:
    assert robot()._next_poll_s(-0.001) == pytest.approx(INTERVAL / 5)
    assert robot()._next_poll_s(-0.5) == INTERVAL
