"""The glue a dispenser's reads account for between them (server/drivers/wear.py)."""

from __future__ import annotations

import pytest

from server.drivers import wear


def read_at(at: float, *, valve_open: bool, flow: float) -> dict:
    return {"status_at": at, "valve_open": valve_open, "flow_ml_min": flow}


def test_the_interval_between_two_open_reads_counts_their_mean_flow() -> None:
    details = read_at(100.0, valve_open=True, flow=60.0)  # 1 ml/s
    wear.glue_held(details, 101.0, 0.0)  # read again 1 s later: the arm stood still
    assert details[wear.GLUE_ML] == pytest.approx(0.5)
    assert details[wear.VALVE_OPEN_S] == pytest.approx(1.0)


def test_without_a_reading_now_the_last_flow_holds_to_the_close() -> None:
    details = read_at(100.0, valve_open=True, flow=60.0)
    wear.glue_held(details, 100.25)  # the driver's own close, read back
    assert details[wear.GLUE_ML] == pytest.approx(0.25)


def test_a_read_that_saw_the_valve_closed_counts_nothing_after_it() -> None:
    details = read_at(100.0, valve_open=False, flow=0.0)
    wear.glue_held(details, 101.0, 60.0)  # opened since: its start is the next read's
    assert wear.GLUE_ML not in details and wear.VALVE_OPEN_S not in details
