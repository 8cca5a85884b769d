"""The journal's tables, each declared once (`declaration.py` says how): its columns with
their SQL and Python types and meanings, its time column, its filters, whether its rows
are sealed. Adding a column is one edit here (with `older_rows` when journals exist
without it); `schema.py` derives the rest from `ALL_TABLES`.

`commits` and `journal_meta` hold the commit chain (`commit_chain.py`): one row per
transaction the writer committed, and where the chain now starts (after retention cut
it, or after it could not be read). `write_check` holds one row, rewritten by each
write that checks a failing journal can write again.
"""

from __future__ import annotations

from server.storage.journal.declaration import Column, Filtered, Table


def _seq() -> Column:
    return Column("seq", "INTEGER PRIMARY KEY AUTOINCREMENT", int, "the row's number, in order")


def _time(meaning: str = "when it happened (Unix seconds)") -> Column:
    return Column("time", "REAL NOT NULL", float, meaning)


OPERATION_KINDS = ("trajectory", "calibrate_robot", "calibrate_camera", "create_workpiece")

EVENTS = Table(
    "events",
    "Every event the worker decided, accepted or refused (replaced by a later row of its id).",
    (
        Column("id", "TEXT PRIMARY KEY", str, "the event's id"),
        _time(),
        Column("type", "TEXT NOT NULL", str, "the event's type, e.g. START_REQUESTED", Filtered()),
        Column(
            "source",
            "TEXT NOT NULL",
            str,
            "who sent the event, matched whole: api:<client address>, mqtt:<token name>, "
            "opcua:<client address>, order, system, operation, robot, glue, camera, ...",
            Filtered(),
        ),
        Column("data", "TEXT NOT NULL", dict, "the event's data"),
        Column(
            "outcome",
            "TEXT NOT NULL",
            str,
            "the worker's verdict",
            Filtered(values=("accepted", "refused")),
        ),
        Column("message", "TEXT NOT NULL", str, "why it was refused, or what it did"),
        Column(
            "state", "TEXT NOT NULL", str, "the cell's state once the event was decided", Filtered()
        ),
    ),
    sealed=True,
    indexes=(("events_time", "time"),),
)

TRANSITIONS = Table(
    "transitions",
    "Every change of the cell's state.",
    (
        _seq(),
        _time(),
        Column("old_state", "TEXT NOT NULL", str, "the state the cell left", Filtered()),
        Column("new_state", "TEXT NOT NULL", str, "the state the cell entered", Filtered()),
        Column(
            "event",
            "TEXT NOT NULL",
            str,
            "the type of the event that caused the transition",
            Filtered(),
        ),
        Column(
            "event_id",
            "TEXT NOT NULL",
            str,
            "the id of that event",
            Filtered(on_json_route=False),
        ),
        Column("time_in_old_state", "REAL NOT NULL", float, "seconds spent in the old state"),
    ),
    sealed=True,
    indexes=(("transitions_time", "time"),),
)

# Not sealed: a row is updated as its run progresses and ends, so a digest taken when
# it was appended would not hold; the commits that change it are still numbered and
# chained.
OPERATIONS = Table(
    "operations",
    "One row per operation run, updated as it progresses and ends.",
    (
        Column("run_id", "TEXT PRIMARY KEY", str, "the run's id"),
        Column("kind", "TEXT NOT NULL", str, "the operation", Filtered(values=OPERATION_KINDS)),
        Column("started_at", "REAL NOT NULL", float, "when it started (Unix seconds)"),
        Column("ended_at", "REAL", float, "when it ended (Unix seconds); NULL while it runs"),
        Column(
            "outcome",
            "TEXT",
            str,
            "how it ended",
            Filtered(values=("completed", "failed", "cancelled", "interrupted")),
        ),
        Column("params", "TEXT NOT NULL", dict, "what it was asked to do"),
        Column("progress", "TEXT", dict, "its latest progress"),
        Column("result", "TEXT", dict, "its result summary"),
        Column("error", "TEXT", str, "why it failed"),
        Column("workpieces", "INTEGER NOT NULL DEFAULT 0", int, "the parts its plan sprays"),
    ),
    time_column="started_at",
    indexes=(("operations_started", "started_at"),),
)

ERRORS = Table(
    "errors",
    "Every fault recorded.",
    (
        _seq(),
        _time(),
        Column("code", "TEXT NOT NULL", str, "the fault code, e.g. EMERGENCY_STOP", Filtered()),
        Column("message", "TEXT NOT NULL", str, "what failed and what to do"),
        Column(
            "component", "TEXT NOT NULL", str, "the component that reported the fault", Filtered()
        ),
        Column(
            "classification",
            "TEXT NOT NULL",
            str,
            "how grave",
            Filtered(values=("critical", "recoverable", "warning")),
        ),
        Column("event_id", "TEXT NOT NULL", str, "the event that recorded it"),
        Column(
            "state",
            "TEXT NOT NULL",
            str,
            "the cell's state when the fault was recorded",
            Filtered(),
        ),
        Column(
            "context",
            "TEXT NOT NULL DEFAULT '{\"operation\": null}'",
            dict,
            "what the fault interrupted: operation, run id, workpiece, waypoint",
            older_rows='{"operation": null}',
        ),
        Column(
            "trace",
            "TEXT NOT NULL DEFAULT ''",
            str,
            "the stack, when an exception caused the fault; empty otherwise",
            older_rows="",
        ),
    ),
    sealed=True,
    indexes=(("errors_time", "time"),),
)

RECOVERIES = Table(
    "recoveries",
    "One in-place retry of a recoverable fault, and whether it succeeded.",
    (
        _seq(),
        _time(),
        Column(
            "run_id", "TEXT NOT NULL", str, "the run of the operation that was retried", Filtered()
        ),
        Column(
            "error_code", "TEXT NOT NULL", str, "the fault code that caused the retry", Filtered()
        ),
        Column("attempt", "INTEGER NOT NULL", int, "the retry's number"),
        Column("succeeded", "INTEGER NOT NULL", bool, "whether the retry succeeded"),
    ),
    sealed=True,
    indexes=(("recoveries_time", "time"),),
)

AUDIT = Table(
    "audit",
    "Who did what, from where, with what outcome.",
    (
        _seq(),
        _time(),
        Column(
            "principal",
            "TEXT NOT NULL",
            str,
            "who: the token's name and role, or anonymous",
            Filtered(),
        ),
        Column("address", "TEXT NOT NULL", str, "the client's address", Filtered()),
        Column("action", "TEXT NOT NULL", str, "what: the method and path", Filtered()),
        Column("outcome", "TEXT NOT NULL", str, "accepted, or refused with the status", Filtered()),
        Column("detail", "TEXT NOT NULL", str, "the change, or why it was refused"),
        Column(
            "count",
            "INTEGER NOT NULL DEFAULT 1",
            int,
            "how many identical refusals the row stands for (server/api/audit_repeats.py)",
            older_rows=1,
        ),
    ),
    sealed=True,
    indexes=(("audit_time", "time"),),
)

WEBHOOK_DELIVERIES = Table(
    "webhook_deliveries",
    "One row per webhook notice, written once its outcome is final (docs/plant-integration.md).",
    (
        _seq(),
        _time("when its outcome became final (Unix seconds)"),
        Column(
            "delivery_id",
            "TEXT NOT NULL",
            str,
            "the notice's id, as the receiver got it",
            Filtered(),
        ),
        Column("webhook", "TEXT NOT NULL", str, "the webhook's name", Filtered()),
        Column(
            "kind",
            "TEXT NOT NULL",
            str,
            "the notice",
            Filtered(values=("fault", "alert", "state", "run_completed", "part", "report")),
        ),
        Column("event_at", "REAL NOT NULL", float, "when what it tells happened (Unix seconds)"),
        Column(
            "outcome",
            "TEXT NOT NULL",
            str,
            "how its delivery ended",
            Filtered(values=("delivered", "refused", "failed", "dropped", "abandoned")),
        ),
        Column("attempts", "INTEGER NOT NULL", int, "how many times it was sent"),
        Column("status", "INTEGER", int, "the last HTTP status the receiver answered"),
        Column("error", "TEXT NOT NULL", str, "the last attempt's error, or empty"),
        Column("tries", "TEXT NOT NULL", list, "each attempt: time, seconds, status, error"),
    ),
    sealed=True,
    indexes=(("webhook_deliveries_time", "time"),),
)

INSPECTIONS = Table(
    "inspections",
    "One row per inspected spray run (docs/quality.md): the whole inspection as JSON.",
    (
        _seq(),
        _time(),
        Column("run_id", "TEXT NOT NULL", str, "the spray run inspected", Filtered()),
        Column(
            "verdict",
            "TEXT NOT NULL",
            str,
            "the part's verdict",
            Filtered(values=("good", "defective")),
        ),
        Column("took_s", "REAL NOT NULL", float, "how long the inspection took"),
        Column("document", "TEXT NOT NULL", dict, "the whole inspection"),
    ),
    sealed=True,
    indexes=(("inspections_time", "time"), ("inspections_run", "run_id")),
)

# Not sealed: a row is updated as its order goes (like `operations`).
ORDERS = Table(
    "orders",
    "Production orders (server/orders/): one row per order, updated as it goes.",
    (
        Column("order_id", "TEXT PRIMARY KEY", str, "the order's id"),
        Column("created_at", "REAL NOT NULL", float, "when it was made (Unix seconds)"),
        Column("workpiece_id", "TEXT NOT NULL", str, "the workpiece the order makes", Filtered()),
        Column("quantity", "INTEGER NOT NULL", int, "how many good parts it makes"),
        Column("defect_limit", "INTEGER NOT NULL", int, "defective parts in a row that stop it"),
        Column(
            "state",
            "TEXT NOT NULL",
            str,
            "the order's state",
            Filtered(values=("queued", "running", "held", "completed", "closed")),
        ),
        Column("reason", "TEXT", str, "why it is held, closed or completed"),
        Column("created_by", "TEXT NOT NULL", str, "who made it"),
        Column("updated_at", "REAL NOT NULL", float, "when it last changed (Unix seconds)"),
        Column(
            "idempotency_key",
            "TEXT",
            str,
            "the Idempotency-Key it was made with: a retry with it gets this order",
            older_rows=None,
        ),
    ),
    time_column="created_at",
    indexes=(("orders_created", "created_at"),),
)

ORDER_PARTS = Table(
    "order_parts",
    "One row per part made for an order.",
    (
        _seq(),
        _time("when its run ended (Unix seconds)"),
        Column("order_id", "TEXT NOT NULL", str, "the order the part was made for", Filtered()),
        Column("run_id", "TEXT NOT NULL", str, "the run that made it"),
        Column("started_at", "REAL", float, "when its run started (Unix seconds)"),
        Column("outcome", "TEXT NOT NULL", str, "how the run ended: completed, failed, cancelled"),
        Column("verdict", "TEXT NOT NULL", str, "good, defective or not_inspected", Filtered()),
        Column("inspected", "INTEGER NOT NULL", bool, "whether its inspection judged it"),
        Column("reasons", "TEXT NOT NULL", list, "why it is defective, or not inspected"),
        Column("precision_mean_mm", "REAL", float, "mean path deviation", part_figure=True),
        Column("precision_p95_mm", "REAL", float, "95th percentile deviation", part_figure=True),
        Column("glue_ml", "REAL", float, "glue dispensed", part_figure=True),
    ),
    sealed=True,
    indexes=(("order_parts_time", "time"),),
)

RUN_SAMPLES = Table(
    "run_samples",
    "The flight recorder: each run's device samples at the live feed's rate "
    "(server/views/recording.py).",
    (
        _seq(),
        _time("when the live feed took the sample (Unix seconds)"),
        Column("run_id", "TEXT NOT NULL", str, "the run the sample belongs to", Filtered()),
        Column("x_mm", "REAL", float, "the tool point's x in the robot's frame; NULL: no pose yet"),
        Column("y_mm", "REAL", float, "the tool point's y in the robot's frame"),
        Column("z_mm", "REAL", float, "the tool point's z in the robot's frame"),
        Column("pose_at", "REAL", float, "when the robot reported that pose (Unix seconds)"),
        Column("speed_mm_s", "REAL", float, "tool speed between the last two poses read"),
        Column("valve_open", "INTEGER NOT NULL", bool, "whether the glue valve was open"),
        Column("flow_ml_min", "REAL", float, "the flow the dispenser measured"),
        Column("pressure_psi", "REAL", float, "the pressure the dispenser measured"),
        Column("glue_at", "REAL", float, "when the dispenser reported them (Unix seconds)"),
    ),
    sealed=True,
    indexes=(("run_samples_time", "time"), ("run_samples_run", "run_id")),
)

REPORTS = Table(
    "reports",
    "Shift and daily reports (server/views/reports.py): one row per report, as made.",
    (
        _seq(),
        _time("when it was made (Unix seconds)"),
        Column("kind", "TEXT NOT NULL", str, "the report", Filtered(values=("shift", "day"))),
        Column("window_start", "REAL NOT NULL", float, "the start of the window it covers"),
        Column("window_end", "REAL NOT NULL", float, "the end of the window (excluded)"),
        Column("document", "TEXT NOT NULL", dict, "the whole report"),
    ),
    sealed=True,
    indexes=(("reports_time", "time"),),
)

COMMITS = Table(
    "commits",
    "The commit chain (commit_chain.py): one row per transaction the writer committed.",
    (
        Column("seq", "INTEGER PRIMARY KEY", int, "the commit's number"),
        _time("when it was committed (Unix seconds)"),
        Column("rows", "TEXT NOT NULL", dict, "rows appended to each sealed table so far"),
        Column("digest", "TEXT NOT NULL", str, "the chained digest"),
    ),
    internal=True,
)

JOURNAL_META = Table(
    "journal_meta",
    "The journal's own facts, such as where the commit chain now starts.",
    (
        Column("key", "TEXT PRIMARY KEY", str, "the fact"),
        Column("value", "TEXT NOT NULL", str, "its value"),
    ),
    time_column=None,
    internal=True,
)

WRITE_CHECK = Table(
    "write_check",
    "One row, rewritten by each write that checks a failing journal can write again.",
    (
        Column("id", "INTEGER PRIMARY KEY CHECK (id = 1)", int, "always 1"),
        _time("when the check wrote (Unix seconds)"),
    ),
    internal=True,
)

WEAR = Table(
    "wear",
    "Wear counters and maintenance marks (server/core/worker/care.py), kept across restarts.",
    (
        Column("key", "TEXT PRIMARY KEY", str, "the counter or mark"),
        Column("value", "REAL NOT NULL", float, "its value"),
        _time("when it was last written (Unix seconds)"),
    ),
    time_column=None,
    internal=True,
)

# Every table, in the order SCHEMA creates them.
ALL_TABLES: tuple[Table, ...] = (
    EVENTS,
    TRANSITIONS,
    OPERATIONS,
    ERRORS,
    RECOVERIES,
    AUDIT,
    WEBHOOK_DELIVERIES,
    INSPECTIONS,
    ORDERS,
    ORDER_PARTS,
    RUN_SAMPLES,
    REPORTS,
    COMMITS,
    JOURNAL_META,
    WRITE_CHECK,
    WEAR,
)
