"""Checks on a journal file (SQLite), shared by the reliability tests and the soak.

Why read the file directly rather than ask the API: these checks judge what the
server *wrote*, the record an operator or an auditor relies on after the fact.
They use the transition table of server/core/machine/transitions.py as data, so a
journaled transition is valid exactly when the table has that row; a new row
in the table is accepted here without editing this module.

Open the file while the server runs or after it stopped: the reader uses its own
connection in WAL mode and only reads.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterable
from pathlib import Path

from server.core.machine.transitions import TRANSITIONS

Triple = tuple[str, str, str]  # (old_state, event, new_state)


def _connect(path: Path) -> sqlite3.Connection:
    if not Path(path).is_file():  # sqlite3.connect would create an empty database
        raise FileNotFoundError(path)
    connection = sqlite3.connect(path, timeout=30)
    connection.execute("PRAGMA query_only=ON")
    return connection


def allowed_transitions() -> set[Triple]:
    """Every (old_state, event, new_state) the table permits."""
    return {
        (row.source.value, row.event.value, row.target.value)
        for rows in TRANSITIONS.values()
        for row in rows.values()
    }


def journaled_transitions(path: Path) -> list[Triple]:
    """Every transition in the journal, oldest first, as (old_state, event, new_state)."""
    connection = _connect(path)
    try:
        rows = connection.execute(
            "SELECT old_state, event, new_state FROM transitions ORDER BY seq"
        ).fetchall()
    finally:
        connection.close()
    return [(str(old), str(event), str(new)) for old, event, new in rows]


def invalid_transitions(path: Path) -> list[Triple]:
    """The journaled transitions that the table does not permit (empty when all are valid)."""
    allowed = allowed_transitions()
    return [triple for triple in journaled_transitions(path) if triple not in allowed]


def journaled_event_ids(path: Path) -> set[str]:
    """The ids of every event in the journal's `events` table."""
    connection = _connect(path)
    try:
        rows = connection.execute("SELECT id FROM events").fetchall()
    finally:
        connection.close()
    return {str(event_id) for (event_id,) in rows}


def missing_events(path: Path, acknowledged: Iterable[str]) -> set[str]:
    """The acknowledged event ids that are not in the journal (lost events)."""
    return set(acknowledged) - journaled_event_ids(path)


def operation_outcomes(path: Path) -> dict[str, int]:
    """How the journaled operations ended: outcome → count ("running" when not ended)."""
    connection = _connect(path)
    try:
        rows = connection.execute(
            "SELECT COALESCE(outcome, 'running'), COUNT(*) FROM operations GROUP BY 1"
        ).fetchall()
    finally:
        connection.close()
    return {str(outcome): int(count) for outcome, count in rows}
