"""What the worker reads for every event is built once and says what building it anew
would: each row's decision (`engine.step`), each row's checkpoint (`decide`), and the
JSON text of a journal column."""

from __future__ import annotations

import json
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest

from server.core.machine import decide
from server.core.machine.actions import EXIT_ACTIONS, actions_of
from server.core.machine.engine import Decision, Facts, step
from server.core.machine.events import NoPayload
from server.core.machine.transitions import TRANSITIONS, Event, State
from server.settings.model import Settings
from server.storage.journal import records

ROWS = [(state, event, row) for state, rows in TRANSITIONS.items() for event, row in rows.items()]
READY = Facts(ready_devices=frozenset({"robot", "glue", "camera"}))


@pytest.mark.parametrize(("state", "event", "row"), ROWS)
def test_each_rows_decision_is_its_row_and_actions_handed_out_once(state, event, row) -> None:
    decision = step(state, event, READY)
    assert decision == Decision(event, row, actions_of(row))
    assert step(state, event, READY) is decision  # the same decision, not a new one


def test_each_rows_checkpoint_is_its_first_action_after_the_exit_actions() -> None:
    """Every row a plain payload is accepted by (a reset in ERROR goes to its probe, a
    start or a jog needs its own payload)."""
    facts, settings = decide.Facts(guards=READY), Settings()
    checked = 0
    for state, event, row in ROWS:
        verdict = decide.decide(state, event, NoPayload(), facts, settings)
        if isinstance(verdict, decide.Accepted):
            actions = actions_of(row)
            first = next((i for i, a in enumerate(actions) if a not in EXIT_ACTIONS), None)
            assert verdict.checkpoint == (None if row.target is State.ERROR else first)
            checked += 1
    assert checked > len(ROWS) // 2


@pytest.mark.parametrize(
    "value",
    [
        {"operation": None},
        {"a": [1, 2.5, "é"], "b": {"c": None, "d": True}},
        {"when": datetime(2026, 1, 2, tzinfo=UTC), "where": Path("/tmp/x")},  # default=str
        [float("inf"), "x"],
        {},
    ],
)
def test_a_json_column_is_the_text_json_dumps_gives(value: Any) -> None:
    text = json.dumps(value, default=str, separators=(",", ":")) if value != {} else "{}"
    assert records._json(value) == text


def test_a_state_or_events_str_is_its_value() -> None:
    """The worker names states and events by `str()` on its per-event path."""
    for member in (*State, *Event):
        assert str(member) == member.value and type(str(member)) is str
