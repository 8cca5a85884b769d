"""The journal's records: one function per kind of row, each a `Record` for the writer.

Callers build records where things happen (the worker, the audit observer) and
hand lists of them to `Journal.append`, which writes each list in one
transaction.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass
from typing import Any

from server.storage.journal.schema import COMMIT_SEQ


@dataclass(frozen=True, slots=True)
class Sealed:
    """How the writer appends a row the commit chain seals (`commit_chain.py`): `sql`
    takes the commit's sequence number as one more parameter."""

    table: str
    sql: str


@dataclass(frozen=True, slots=True)
class Record:
    """One SQL statement for the writer: `sql` with `params` (also runnable as it is).

    `sealed`, on a row of a sealed table, is the form the writer runs instead.
    """

    sql: str
    params: tuple[Any, ...]
    sealed: Sealed | None = None


def _appended(
    table: str, columns: tuple[str, ...], values: tuple[Any, ...], *, replace: bool = False
) -> Record:
    """A row of a sealed `table`: `values` for `columns`."""
    sql, sealed = _statements(table, columns, replace)
    return Record(sql, values, sealed)


@functools.cache
def _statements(table: str, columns: tuple[str, ...], replace: bool) -> tuple[str, Sealed]:
    """The SQL of a row of `table` (plain and sealed): built once per kind of row, not per
    row, since every event the worker decides writes one or more."""
    verb = "INSERT OR REPLACE" if replace else "INSERT"
    placeholders = ",".join("?" * len(columns))
    sealed = f"{verb} INTO {table} ({', '.join(columns)}, {COMMIT_SEQ}) VALUES ({placeholders},?)"
    plain = f"{verb} INTO {table} ({', '.join(columns)}) VALUES ({placeholders})"
    return plain, Sealed(table, sealed)


def _json(value: Any) -> str:
    if value == {}:  # most events carry no data: no encoder for them
        return "{}"
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
    return _appended(
        "events",
        ("id", "time", "type", "source", "data", "outcome", "message", "state"),
        (event_id, at, type_, source, _json(data), outcome, message, state),
        replace=True,
    )


def transition(row: dict[str, Any]) -> Record:
    """A transition, from its dict (timestamp, old_state, new_state, event, event_id,
    time_in_old_state)."""
    return _appended(
        "transitions",
        ("time", "old_state", "new_state", "event", "event_id", "time_in_old_state"),
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


def operation_planned(run_id: str, workpieces: int) -> Record:
    """The parts a run's plan sprays, before it sprays them (its end may never be recorded)."""
    return Record(
        "UPDATE operations SET workpieces = ? WHERE run_id = ? AND ended_at IS NULL",
        (workpieces, run_id),
    )


def operation_ended(
    run_id: str, at: float, outcome: str, result: Any, error: str | None, workpieces: int
) -> Record:
    """How an operation ended (a row already closed is left as it is)."""
    return Record(
        "UPDATE operations SET ended_at = ?, outcome = ?, result = ?, error = ?, "
        "workpieces = ? WHERE run_id = ? AND ended_at IS NULL",
        (at, outcome, _json(result), error, workpieces, run_id),
    )


def inspection(at: float, run_id: str, document: dict[str, Any]) -> Record:
    """A spray run's whole inspection (server/quality/), sealed like the other appended rows."""
    return _appended(
        "inspections",
        ("time", "run_id", "verdict", "took_s", "document"),
        (at, run_id, document["verdict"], float(document["took_s"]), _json(document)),
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
    return _appended(
        "errors",
        ("time", "code", "message", "component", "classification", "event_id", "state"),
        (at, code, message, component, classification, event_id, state),
    )


def recovery(at: float, run_id: str, error_code: str, attempt: int, succeeded: bool) -> Record:
    """One in-place retry of a recoverable fault, and whether it succeeded."""
    return _appended(
        "recoveries",
        ("time", "run_id", "error_code", "attempt", "succeeded"),
        (at, run_id, error_code, attempt, int(succeeded)),
    )


def audit(
    at: float,
    principal: str,
    address: str,
    action: str,
    outcome: str,
    detail: str,
    count: int = 1,
) -> Record:
    """Who did what, from where, with what outcome; `count` identical refusals folded in one
    (server/api/audit_repeats.py)."""
    if count == 1:  # the row as it always was: digested as before the column (sealed_form)
        return _appended(
            "audit",
            ("time", "principal", "address", "action", "outcome", "detail"),
            (at, principal, address, action, outcome, detail),
        )
    return _appended(
        "audit",
        ("time", "principal", "address", "action", "outcome", "detail", "count"),
        (at, principal, address, action, outcome, detail, count),
    )


def write_check(at: float) -> Record:
    """A real write that leaves nothing behind but its time: does the journal write again?"""
    return Record("INSERT OR REPLACE INTO write_check (id, time) VALUES (1, ?)", (at,))


def webhook_delivery(
    at: float,
    delivery_id: str,
    webhook: str,
    kind: str,
    event_at: float,
    outcome: str,
    tries: list[dict[str, Any]],
    error: str,
) -> Record:
    """A webhook notice's final outcome, with each attempt (time, seconds, status, error)."""
    status = tries[-1].get("status") if tries else None
    return _appended(
        "webhook_deliveries",
        (
            "time",
            "delivery_id",
            "webhook",
            "kind",
            "event_at",
            "outcome",
            "attempts",
            "status",
            "error",
            "tries",
        ),
        (
            at,
            delivery_id,
            webhook,
            kind,
            event_at,
            outcome,
            len(tries),
            status,
            error,
            _json(tries),
        ),
    )


def order(
    order_id: str,
    created_at: float,
    workpiece_id: str,
    quantity: int,
    defect_limit: int,
    state: str,
    reason: str | None,
    created_by: str,
    updated_at: float,
) -> Record:
    """A production order as it now stands (replaces its earlier row: it is updated as it
    goes, so `orders` is not sealed)."""
    return Record(
        "INSERT OR REPLACE INTO orders (order_id, created_at, workpiece_id, quantity, "
        "defect_limit, state, reason, created_by, updated_at) VALUES (?,?,?,?,?,?,?,?,?)",
        (
            order_id,
            created_at,
            workpiece_id,
            quantity,
            defect_limit,
            state,
            reason,
            created_by,
            updated_at,
        ),
    )


def order_part(
    at: float,
    order_id: str,
    run_id: str,
    started_at: float | None,
    outcome: str,
    verdict: str,
    inspected: bool,
    reasons: list[str],
    precision_mean_mm: float | None,
    precision_p95_mm: float | None,
    glue_ml: float | None,
) -> Record:
    """One part made for an order: its run, how the run ended and the part's verdict."""
    return _appended(
        "order_parts",
        (
            "time",
            "order_id",
            "run_id",
            "started_at",
            "outcome",
            "verdict",
            "inspected",
            "reasons",
            "precision_mean_mm",
            "precision_p95_mm",
            "glue_ml",
        ),
        (
            at,
            order_id,
            run_id,
            started_at,
            outcome,
            verdict,
            int(inspected),
            _json(reasons),
            precision_mean_mm,
            precision_p95_mm,
            glue_ml,
        ),
    )
