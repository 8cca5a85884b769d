"""The journal's records: one function per kind of row, each a `Record` for the writer.

Each builds its row by column name through `_row` (or `_update`), which takes the
columns, their order and how each is stored (JSON text, 0 or 1) from the table's
declaration in `tables.py`, and refuses a name the table does not declare.

Callers build records where things happen (the worker, the audit observer) and
hand lists of them to `Journal.append`, which writes each list in one
transaction.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from server.storage.journal.declaration import Column
from server.storage.journal.schema import COMMIT_SEQ, INTERNAL, TABLES


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


def _row(table: str, *, replace: bool = False, **values: Any) -> Record:
    """A row of `table` (tables.py): `values` by column name, in the order given, JSON and
    flag columns encoded as the declaration says; the columns not given take their SQL
    default. Sealed when the table is."""
    return _statement(table, tuple(values), replace).row(tuple(values.values()))


@dataclass(frozen=True, slots=True)
class _Statement:
    """One kind of row of a table: its SQL, checked against the declaration once, and the
    encoders of its JSON and flag columns."""

    sql: str
    sealed: Sealed | None
    encoders: tuple[tuple[int, Callable[[Any], Any]], ...]  # (position, encoder) to apply

    def row(self, values: tuple[Any, ...]) -> Record:
        """The record of a row giving `values`, in the statement's column order."""
        if self.encoders:
            params = list(values)
            for at, encode in self.encoders:
                params[at] = encode(params[at])
            values = tuple(params)
        return Record(self.sql, values, self.sealed)


@functools.cache
def _statement(table: str, given: tuple[str, ...], replace: bool) -> _Statement:
    """The SQL of a row of `table` giving the columns `given` (plain, and sealed when the
    table is): built once per kind of row, not per row, since every event the worker
    decides writes one or more. A name the table does not declare, or a column it needs
    that is not given, is a programming error caught at the first row."""
    declared = TABLES.get(table) or INTERNAL[table]
    unknown = set(given) - set(declared.column_names)
    if unknown:
        raise ValueError(f"{table} has no column {', '.join(sorted(unknown))}")
    missing = [
        c.name
        for c in declared.columns
        if c.name not in given and not (c.nullable or c.generated or "DEFAULT" in c.sql)
    ]
    if missing:
        raise ValueError(f"a row of {table} needs {', '.join(missing)}")
    names = ", ".join(given)
    placeholders = ",".join("?" * len(given))
    verb = "INSERT OR REPLACE" if replace else "INSERT"
    plain = f"{verb} INTO {table} ({names}) VALUES ({placeholders})"
    sealed = None
    if declared.sealed:
        sql = f"{verb} INTO {table} ({names}, {COMMIT_SEQ}) VALUES ({placeholders},?)"
        sealed = Sealed(table, sql)
    encoders = (
        (at, encode)
        for at, name in enumerate(given)
        if (encode := _encoder(declared.column(name))) is not _same
    )
    return _Statement(plain, sealed, tuple(encoders))


def _encoder(column: Column) -> Callable[[Any], Any]:
    """How a value of `column` is stored: JSON text, 0 or 1, or as it is."""
    if column.json:
        return _json
    if column.py is bool:
        return int
    return _same


def _same(value: Any) -> Any:
    return value


def _update(table: str, where: str, key: Any, **values: Any) -> Record:
    """An UPDATE of the declared columns `values` of `table`'s rows matching `where`
    (one placeholder, `key`)."""
    return _update_statement(table, where, tuple(values)).row((*values.values(), key))


@functools.cache
def _update_statement(table: str, where: str, given: tuple[str, ...]) -> _Statement:
    """The SQL of an UPDATE of the columns `given`, built once per kind of update (a run's
    end, its progress): its values are the columns', then the key of `where`."""
    declared = TABLES[table]
    assignments = ", ".join(f"{name} = ?" for name in given)
    encoders = (
        (at, encode)
        for at, name in enumerate(given)
        if (encode := _encoder(declared.column(name))) is not _same
    )
    return _Statement(f"UPDATE {table} SET {assignments} WHERE {where}", None, tuple(encoders))


def _json(value: Any) -> str:
    if value == {}:  # most events carry no data: no encoder for them
        return "{}"
    return _ENCODER.encode(value)


# What `json.dumps(value, default=str, separators=(",", ":"))` would build for every
# value, built once: the encoder keeps no state between calls, and a JSON column is
# written with most events the worker decides.
_ENCODER = json.JSONEncoder(default=str, separators=(",", ":"))


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
    return _EVENT.row((event_id, at, type_, source, data, outcome, message, state))


# The rows the worker writes for every event it decides (and for every fault), their
# statements built at import.
_EVENT = _statement(
    "events", ("id", "time", "type", "source", "data", "outcome", "message", "state"), True
)
_TRANSITION = _statement(
    "transitions",
    ("time", "old_state", "new_state", "event", "event_id", "time_in_old_state"),
    False,
)


def transition(row: dict[str, Any]) -> Record:
    """A transition, from its dict (timestamp, old_state, new_state, event, event_id,
    time_in_old_state)."""
    return _TRANSITION.row(
        (
            row["timestamp"],
            row["old_state"],
            row["new_state"],
            row["event"],
            row["event_id"],
            row["time_in_old_state"],
        )
    )


def operation_started(run_id: str, kind: str, at: float, params: dict[str, Any]) -> Record:
    """An operation's row, open until `operation_ended`."""
    return _row("operations", replace=True, run_id=run_id, kind=kind, started_at=at, params=params)


def operation_progress(run_id: str, progress: dict[str, Any]) -> Record:
    """A running operation's latest progress."""
    return _update("operations", "run_id = ?", run_id, progress=progress)


def operation_planned(run_id: str, workpieces: int) -> Record:
    """The parts a run's plan sprays, before it sprays them (its end may never be recorded)."""
    return _update("operations", _OPEN_RUN, run_id, workpieces=workpieces)


def operation_ended(
    run_id: str, at: float, outcome: str, result: Any, error: str | None, workpieces: int
) -> Record:
    """How an operation ended (a row already closed is left as it is)."""
    return _update(
        "operations",
        _OPEN_RUN,
        run_id,
        ended_at=at,
        outcome=outcome,
        result=result,
        error=error,
        workpieces=workpieces,
    )


_OPEN_RUN = "run_id = ? AND ended_at IS NULL"


def inspection(at: float, run_id: str, document: dict[str, Any]) -> Record:
    """A spray run's whole inspection (server/quality/), sealed like the other appended rows."""
    return _row(
        "inspections",
        time=at,
        run_id=run_id,
        verdict=document["verdict"],
        took_s=float(document["took_s"]),
        document=document,
    )


def error(
    at: float,
    code: str,
    message: str,
    component: str,
    classification: str,
    event_id: str,
    state: str,
    context: dict[str, Any] | None = None,
    trace: str = "",
) -> Record:
    """A fault or warning, with what it interrupted (None: no operation) and the stack
    when an exception caused it."""
    context = context if context is not None else {"operation": None}
    return _ERROR.row(
        (at, code, message, component, classification, event_id, state, context, trace)
    )


_ERROR = _statement(
    "errors",
    (
        "time",
        "code",
        "message",
        "component",
        "classification",
        "event_id",
        "state",
        "context",
        "trace",
    ),
    False,
)


def recovery(at: float, run_id: str, error_code: str, attempt: int, succeeded: bool) -> Record:
    """One in-place retry of a recoverable fault, and whether it succeeded."""
    return _row(
        "recoveries",
        time=at,
        run_id=run_id,
        error_code=error_code,
        attempt=attempt,
        succeeded=succeeded,
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
    (server/api/audit_repeats.py). A single one leaves `count` to its default, as the row
    was before the column (sealed_form digests it so)."""
    folded: dict[str, Any] = {} if count == 1 else {"count": count}
    return _row(
        "audit",
        time=at,
        principal=principal,
        address=address,
        action=action,
        outcome=outcome,
        detail=detail,
        **folded,
    )


def write_check(at: float) -> Record:
    """A real write that leaves nothing behind but its time: does the journal write again?"""
    return _row("write_check", replace=True, id=1, time=at)


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
    return _row(
        "webhook_deliveries",
        time=at,
        delivery_id=delivery_id,
        webhook=webhook,
        kind=kind,
        event_at=event_at,
        outcome=outcome,
        attempts=len(tries),
        status=tries[-1].get("status") if tries else None,
        error=error,
        tries=tries,
    )


def order(**columns: Any) -> Record:
    """A production order as it now stands, every column of `orders` by name (replaces its
    earlier row: it is updated as it goes, so `orders` is not sealed)."""
    return _row("orders", replace=True, **columns)


def order_part(**columns: Any) -> Record:
    """One part made for an order, the columns of `order_parts` by name: its run, how the
    run ended, the part's verdict and its inspection figures."""
    return _row("order_parts", **columns)


def wear(key: str, value: float, at: float) -> Record:
    """A wear counter or maintenance mark (`wear` table), replacing the one of its key."""
    return _row("wear", replace=True, key=key, value=float(value), time=at)


def run_sample(**columns: Any) -> Record:
    """One device sample of a run (the flight recorder), the columns of `run_samples` by
    name."""
    return _row("run_samples", **columns)


def report(**columns: Any) -> Record:
    """A shift or daily report as made, the columns of `reports` by name."""
    return _row("reports", **columns)
