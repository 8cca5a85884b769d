"""The dispenser's open time and glue between two status reads (server/drivers/wear.py)."""

from __future__ import annotations

import pytest

from server.drivers import glue_registers as regs
from server.drivers import wear


def read_at(at: float, *, valve_open: bool, total_ml: float | None = 10.0) -> dict:
    return {"status_at": at, "valve_open": valve_open, "dispensed_ml": total_ml}


def test_the_interval_after_an_open_read_counts_as_open_time() -> None:
    details = read_at(100.0, valve_open=True)
    wear.valve_open_held(details, 101.0)
    assert details[wear.VALVE_OPEN_S] == pytest.approx(1.0)


def test_a_read_that_saw_the_valve_closed_counts_no_open_time_after_it() -> None:
    details = read_at(100.0, valve_open=False)
    wear.valve_open_held(details, 101.0)  # opened since: its start is the next read's
    assert wear.VALVE_OPEN_S not in details


def test_the_glue_is_what_the_totaliser_grew_by_however_far_apart_the_reads() -> None:
    details = read_at(100.0, valve_open=True, total_ml=10.0)
    wear.glue_counted(details, 11.25)
    assert details[wear.GLUE_ML] == pytest.approx(1.25)


def test_a_count_that_wrapped_adds_what_it_counted_across_the_wrap() -> None:
    top = regs.TOTAL_WRAP_ML - 0.5
    details = read_at(100.0, valve_open=True, total_ml=top)
    wear.glue_counted(details, 0.25)
    assert details[wear.GLUE_ML] == pytest.approx(0.75)


def test_a_count_that_started_again_adds_what_it_counted_since_power_up() -> None:
    details = read_at(100.0, valve_open=False, total_ml=5000.0)
    wear.glue_counted(details, 0.4)  # the dispenser was powered up again
    assert details[wear.GLUE_ML] == pytest.approx(0.4)


def test_no_count_without_a_totaliser_or_before_the_first_read() -> None:
    details = read_at(100.0, valve_open=True, total_ml=None)
    wear.glue_counted(details, 3.0)
    first = {"status_at": 100.0, "valve_open": True}  # no read has given a count yet
    wear.glue_counted(first, 3.0)
    keeps_none = read_at(100.0, valve_open=True)
    wear.glue_counted(keeps_none, None)
    assert wear.GLUE_ML not in details and wear.GLUE_ML not in first
    assert wear.GLUE_ML not in keeps_none
