"""The journal's tables: their SQL, their columns, and what a query may filter on.

`FILTERS` is the one declaration of each table's equality filters: the readers
refuse any other column, and the HTTP routes (server/api/analytics.py) build
their query parameters, with type and description, from it.

`commits` and `journal_meta` hold the commit chain (`commit_chain.py`): one row
per transaction the writer committed, and where the chain now starts (after
retention cut it, or after it could not be read).
"""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass
from typing import Any

SCHEMA = """
CREATE TABLE IF NOT EXISTS events (
    id TEXT PRIMARY KEY, time REAL NOT NULL, type TEXT NOT NULL, source TEXT NOT NULL,
    data TEXT NOT NULL, outcome TEXT NOT NULL, message TEXT NOT NULL, state TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS transitions (
    seq INTEGER PRIMARY KEY AUTOINCREMENT, time REAL NOT NULL, old_state TEXT NOT NULL,
    new_state TEXT NOT NULL, event TEXT NOT NULL, event_id TEXT NOT NULL,
    time_in_old_state REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS operations (
    run_id TEXT PRIMARY KEY, kind TEXT NOT NULL, started_at REAL NOT NULL, ended_at REAL,
    outcome TEXT, params TEXT NOT NULL, progress TEXT, result TEXT, error TEXT,
    workpieces INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS errors (
    seq INTEGER PRIMARY KEY AUTOINCREMENT, time REAL NOT NULL, code TEXT NOT NULL,
    message TEXT NOT NULL, component TEXT NOT NULL, classification TEXT NOT NULL,
    event_id TEXT NOT NULL, state TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS recoveries (
    seq INTEGER PRIMARY KEY AUTOINCREMENT, time REAL NOT NULL, run_id TEXT NOT NULL,
    error_code TEXT NOT NULL, attempt INTEGER NOT NULL, succeeded INTEGER NOT NULL
);
-- count: how many identical refusals the row stands for (server/api/audit_repeats.py).
CREATE TABLE IF NOT EXISTS audit (
    seq INTEGER PRIMARY KEY AUTOINCREMENT, time REAL NOT NULL, principal TEXT NOT NULL,
    address TEXT NOT NULL, action TEXT NOT NULL, outcome TEXT NOT NULL, detail TEXT NOT NULL,
    count INTEGER NOT NULL DEFAULT 1
);
-- One row per webhook notice, written once its outcome is final (docs/plant-integration.md).
CREATE TABLE IF NOT EXISTS webhook_deliveries (
    seq INTEGER PRIMARY KEY AUTOINCREMENT, time REAL NOT NULL, delivery_id TEXT NOT NULL,
    webhook TEXT NOT NULL, kind TEXT NOT NULL, event_at REAL NOT NULL, outcome TEXT NOT NULL,
    attempts INTEGER NOT NULL, status INTEGER, error TEXT NOT NULL, tries TEXT NOT NULL
);
-- One row per inspected spray run (docs/quality.md): the whole inspection as JSON.
CREATE TABLE IF NOT EXISTS inspections (
    seq INTEGER PRIMARY KEY AUTOINCREMENT, time REAL NOT NULL, run_id TEXT NOT NULL,
    verdict TEXT NOT NULL, took_s REAL NOT NULL, document TEXT NOT NULL
);
-- Production orders (server/orders/): one row per order, updated as it goes (like
-- operations), and one row per part made for it.
CREATE TABLE IF NOT EXISTS orders (
    order_id TEXT PRIMARY KEY, created_at REAL NOT NULL, workpiece_id TEXT NOT NULL,
    quantity INTEGER NOT NULL, defect_limit INTEGER NOT NULL, state TEXT NOT NULL,
    reason TEXT, created_by TEXT NOT NULL, updated_at REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS order_parts (
    seq INTEGER PRIMARY KEY AUTOINCREMENT, time REAL NOT NULL, order_id TEXT NOT NULL,
    run_id TEXT NOT NULL, started_at REAL, outcome TEXT NOT NULL, verdict TEXT NOT NULL,
    inspected INTEGER NOT NULL, reasons TEXT NOT NULL, precision_mean_mm REAL,
    precision_p95_mm REAL, glue_ml REAL
);
CREATE TABLE IF NOT EXISTS commits (
    seq INTEGER PRIMARY KEY, time REAL NOT NULL, rows TEXT NOT NULL, digest TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS journal_meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE INDEX IF NOT EXISTS audit_time ON audit(time);
CREATE INDEX IF NOT EXISTS events_time ON events(time);
CREATE INDEX IF NOT EXISTS transitions_time ON transitions(time);
CREATE INDEX IF NOT EXISTS operations_started ON operations(started_at);
CREATE INDEX IF NOT EXISTS errors_time ON errors(time);
CREATE INDEX IF NOT EXISTS recoveries_time ON recoveries(time);
CREATE INDEX IF NOT EXISTS webhook_deliveries_time ON webhook_deliveries(time);
CREATE INDEX IF NOT EXISTS inspections_time ON inspections(time);
CREATE INDEX IF NOT EXISTS inspections_run ON inspections(run_id);
CREATE INDEX IF NOT EXISTS orders_created ON orders(created_at);
CREATE INDEX IF NOT EXISTS order_parts_time ON order_parts(time);
-- One row, rewritten by each write that checks a failing journal can write again.
CREATE TABLE IF NOT EXISTS write_check (id INTEGER PRIMARY KEY CHECK (id = 1), time REAL NOT NULL);
"""

# Per table: its time column (ranges, order, retention) and its columns, in the
# order rows are read and exported.
TABLES: dict[str, tuple[str, list[str]]] = {
    "events": ("time", ["id", "time", "type", "source", "data", "outcome", "message", "state"]),
    "transitions": (
        "time",
        ["seq", "time", "old_state", "new_state", "event", "event_id", "time_in_old_state"],
    ),
    "operations": (
        "started_at",
        [
            "run_id",
            "kind",
            "started_at",
            "ended_at",
            "outcome",
            "params",
            "progress",
            "result",
            "error",
            "workpieces",
        ],
    ),
    "errors": (
        "time",
        ["seq", "time", "code", "message", "component", "classification", "event_id", "state"],
    ),
    "recoveries": ("time", ["seq", "time", "run_id", "error_code", "attempt", "succeeded"]),
    "audit": (
        "time",
        ["seq", "time", "principal", "address", "action", "outcome", "detail", "count"],
    ),
    "webhook_deliveries": (
        "time",
        [
            "seq",
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
        ],
    ),
    "inspections": ("time", ["seq", "time", "run_id", "verdict", "took_s", "document"]),
    "orders": (
        "created_at",
        [
            "order_id",
            "created_at",
            "workpiece_id",
            "quantity",
            "defect_limit",
            "state",
            "reason",
            "created_by",
            "updated_at",
        ],
    ),
    "order_parts": (
        "time",
        [
            "seq",
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
        ],
    ),
}

# The tables whose rows are sealed: each row carries the sequence number of the
# commit that appended it (`commit_seq`, added to older journals at open) and
# is part of that commit's digest. Not `operations`: its rows are updated as a
# run progresses and ends, so a digest taken when a row was appended would not
# hold; the commits that change it are still numbered and chained.
# Nor `orders`, updated as an order goes, for the same reason.
# A table added later (webhook_deliveries, inspections, order_parts) is created at open with
# its commit_seq added like the others', and counts from 0 in the first commit that appends
# to it.
SEALED: tuple[str, ...] = (
    "events",
    "transitions",
    "errors",
    "recoveries",
    "audit",
    "webhook_deliveries",
    "inspections",
    "order_parts",
)
COMMIT_SEQ = "commit_seq"

# Columns added to a table after journals were written without them: added at open,
# with the value every older row takes. A sealed row is digested without such a
# column while it holds that value (`sealed_form`), so older commits verify as before.
LATER_COLUMNS: dict[str, tuple[tuple[str, str, object], ...]] = {
    "audit": (("count", "INTEGER NOT NULL DEFAULT 1", 1),),
}


def add_commit_seq(connection: sqlite3.Connection) -> None:
    """Give each sealed table its `commit_seq` column where an older journal lacks it,
    and each table the LATER_COLUMNS it lacks."""
    for table in SEALED:
        columns = {row[1] for row in connection.execute(f"PRAGMA table_info({table})")}
        if COMMIT_SEQ not in columns:
            connection.execute(f"ALTER TABLE {table} ADD COLUMN {COMMIT_SEQ} INTEGER")
    for table, later in LATER_COLUMNS.items():
        columns = {row[1] for row in connection.execute(f"PRAGMA table_info({table})")}
        for name, declaration, _ in later:
            if name not in columns:
                connection.execute(f"ALTER TABLE {table} ADD COLUMN {name} {declaration}")


def stored_columns(connection: sqlite3.Connection, table: str) -> str:
    """TABLES' columns of `table` for a SELECT, a LATER_COLUMNS one the file does not have
    yet as its default (the journal is verified before it is opened and given it)."""
    have = {row[1] for row in connection.execute(f"PRAGMA table_info({table})")}
    defaults = {name: default for name, _, default in LATER_COLUMNS.get(table, ())}
    return ", ".join(
        name if name in have or name not in defaults else f"{defaults[name]!r} AS {name}"
        for name in TABLES[table][1]
    )


def sealed_form(table: str, row: tuple[Any, ...]) -> tuple[Any, ...]:
    """A row (TABLES' columns) as the commit chain digests it: a LATER_COLUMNS column that
    ends the row and holds its default is left out, as the row was before the column was."""
    later = LATER_COLUMNS.get(table)
    if later is None:
        return row
    for _, _, default in reversed(later):
        if row and row[-1] == default:
            row = row[:-1]
        else:
            break
    return row


@dataclass(frozen=True, slots=True)
class Filter:
    """A column a query may filter on by equality."""

    column: str
    type: type  # of the value compared with the column
    meaning: str  # one line: what the column holds (documents the query parameter)
    # False: only the CSV export offers it, not the table's JSON route (which never did).
    on_json_route: bool = True
    # The values the column can hold, when they are a closed set: any other is a 422
    # naming the parameter (a typo such as outcome=faild matched no row, silently).
    values: tuple[str, ...] = ()


OPERATION_KINDS = ("trajectory", "calibrate_robot", "calibrate_camera", "create_workpiece")

FILTERS: dict[str, tuple[Filter, ...]] = {
    "events": (
        Filter("type", str, "the event's type, e.g. START_REQUESTED"),
        Filter(
            "source",
            str,
            "who sent the event, matched whole: api:<client address>, mqtt:<token name>, "
            "opcua:<client address>, order, system, operation, robot, glue, camera, ...",
        ),
        Filter("outcome", str, "the worker's verdict", values=("accepted", "refused")),
        Filter("state", str, "the cell's state once the event was decided"),
    ),
    "transitions": (
        Filter("old_state", str, "the state the cell left"),
        Filter("new_state", str, "the state the cell entered"),
        Filter("event", str, "the type of the event that caused the transition"),
        Filter("event_id", str, "the id of that event", on_json_route=False),
    ),
    "operations": (
        Filter("kind", str, "the operation", values=OPERATION_KINDS),
        Filter(
            "outcome",
            str,
            "how it ended",
            values=("completed", "failed", "cancelled", "interrupted"),
        ),
    ),
    "errors": (
        Filter("code", str, "the fault code, e.g. EMERGENCY_STOP"),
        Filter("component", str, "the component that reported the fault"),
        Filter("classification", str, "how grave", values=("critical", "recoverable", "warning")),
        Filter("state", str, "the cell's state when the fault was recorded"),
    ),
    "recoveries": (
        Filter("run_id", str, "the run of the operation that was retried"),
        Filter("error_code", str, "the fault code that caused the retry"),
    ),
    "audit": (
        Filter("principal", str, "who: the token's name and role, or anonymous"),
        Filter("address", str, "the client's address"),
        Filter("action", str, "what: the method and path"),
        Filter("outcome", str, "accepted, or refused with the status"),
    ),
    "webhook_deliveries": (
        Filter("webhook", str, "the webhook's name"),
        Filter("kind", str, "the notice", values=("fault", "alert", "state", "run_completed")),
        Filter(
            "outcome",
            str,
            "how its delivery ended",
            values=("delivered", "refused", "failed", "dropped", "abandoned"),
        ),
        Filter("delivery_id", str, "the notice's id, as the receiver got it"),
    ),
    "inspections": (
        Filter("run_id", str, "the spray run inspected"),
        Filter("verdict", str, "the part's verdict", values=("good", "defective")),
    ),
    "orders": (
        Filter("workpiece_id", str, "the workpiece the order makes"),
        Filter(
            "state",
            str,
            "the order's state",
            values=("queued", "running", "held", "completed", "closed"),
        ),
    ),
    "order_parts": (
        Filter("order_id", str, "the order the part was made for"),
        Filter("verdict", str, "good or defective"),
    ),
}


def filter_columns(table: str) -> tuple[str, ...]:
    """The names of the columns `table` may be filtered on."""
    return tuple(f.column for f in FILTERS[table])
