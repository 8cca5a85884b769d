"""The driver polls a move's end where it is due, not up to a poll interval after it
(server/drivers/move_timing.py)."""

from __future__ import annotations

import pytest

from server.drivers.move_timing import FINE_POLL_SHARE, next_poll_s

pytestmark = pytest.mark.unit

INTERVAL = 0.01


def test_a_move_far_from_its_end_is_polled_every_interval() -> None:
    assert next_poll_s(1.0, INTERVAL) == INTERVAL


def test_the_poll_due_after_the_expected_end_lands_on_it() -> None:
    assert next_poll_s(0.004, INTERVAL) == pytest.approx(0.004)


def test_an_arm_a_little_late_is_polled_finely_then_at_the_interval_again() -> None:
    assert next_poll_s(-0.001, INTERVAL) == pytest.approx(INTERVAL * FINE_POLL_SHARE)
    assert next_poll_s(-0.5, INTERVAL) == INTERVAL
