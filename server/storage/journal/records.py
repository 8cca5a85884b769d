"""The journal's records: one function per kind of row, each a `Record` for the writer.

Callers build records where things happen (the worker, the audit observer) and
hand lists of them to `Journal.append`, which writes each list in one
transaction.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True, slots=True)
class Record:
    """One SQL statement for the writer: `sql` with `params`."""

    sql: str
    params: tuple[Any, ...]


def _json(value: Any) -> str:
    return json.dumps(value, default=str, separators=(",", ":"))


def event(
    event_id: str,
    at: float,
    type_: str,
    source: str,
    data: dict[str, Any],
    outcome: str,
    message: str,
    state: str,
) -> Record:
    """An event the worker decided (replaces a row of the same id)."""
    return Record(
        "INSERT OR REPLACE INTO events VALUES (?,?,?,?,?,?,?,?)",
        (event_id, at, type_, source, _json(data), outcome, message, state),
    )


def transition(row: dict[str, Any]) -> Record:
    """A transition, from its dict (timestamp, old_state, new_state, event, event_id,
    time_in_old_state)."""
    return Record(
        "INSERT INTO transitions (time, old_state, new_state, event, event_id, "
        "time_in_old_state) VALUES (?,?,?,?,?,?)",
        (
            row["timestamp"],
            row["old_state"],
            row["new_state"],
            row["event"],
            row["event_id"],
            row["time_in_old_state"],
        ),
    )


def operation_started(run_id: str, kind: str, at: float, params: dict[str, Any]) -> Record:
    """An operation's row, open until `operation_ended`."""
    return Record(
        "INSERT OR REPLACE INTO operations (run_id, kind, started_at, params) VALUES (?,?,?,?)",
        (run_id, kind, at, _json(params)),
    )


def operation_progress(run_id: str, progress: dict[str, Any]) -> Record:
    """A running operation's latest progress."""
    return Record("UPDATE operations SET progress = ? WHERE run_id = ?", (_json(progress), run_id))


def operation_ended(
    run_id: str, at: float, outcome: str, result: Any, error: str | None, workpieces: int
) -> Record:
    """How an operation ended (a row already closed is left as it is)."""
    return Record(
        "UPDATE operations SET ended_at = ?, outcome = ?, result = ?, error = ?, "
        "workpieces = ? WHERE run_id = ? AND ended_at IS NULL",
        (at, outcome, _json(result), error, workpieces, run_id),
    )


def error(
    at: float,
    code: str,
    message: str,
    component: str,
    classification: str,
    event_id: str,
    state: str,
) -> Record:
    """A fault."""
    return Record(
        "INSERT INTO errors (time, code, message, component, classification, event_id, "
        "state) VALUES (?,?,?,?,?,?,?)",
        (at, code, message, component, classification, event_id, state),
    )


def recovery(at: float, run_id: str, error_code: str, attempt: int, succeeded: bool) -> Record:
    """One in-place retry of a recoverable fault, and whether it succeeded."""
    return Record(
        "INSERT INTO recoveries (time, run_id, error_code, attempt, succeeded) VALUES (?,?,?,?,?)",
        (at, run_id, error_code, attempt, int(succeeded)),
    )


def audit(
    at: float, principal: str, address: str, action: str, outcome: str, detail: str
) -> Record:
    """Who did what, from where, with what outcome."""
    return Record(
        "INSERT INTO audit (time, principal, address, action, outcome, detail) "
        "VALUES (?,?,?,?,?,?)",
        (at, principal, address, action, outcome, detail),
    )


def write_check(at: float) -> Record:
    """A real write that leaves nothing behind but its time: does the journal write again?"""
    return Record("INSERT OR REPLACE INTO write_check (id, time) VALUES (1, ?)", (at,))
