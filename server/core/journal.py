"""The journal: every event, transition, operation and error, in SQLite, durably.

Why a writer thread with group commit: SQLite writes (and their fsync) must
never run on the event loop, and the worker must never wait for the disk. The
worker hands records to `append`, which returns a future; the writer thread
takes everything queued, writes it in one transaction, commits, then resolves
those futures. A command's HTTP answer waits for that future, so **an event the
API acknowledged is on disk when the acknowledgement leaves**, while the
worker goes on with the next event and a slow disk delays answers, never
decisions or the emergency stop.

Durability is the `journal_synchronous` setting (SQLite PRAGMA synchronous in
WAL mode): FULL (default) fsyncs the WAL at every commit and survives power
loss; NORMAL survives a crash of the server process but may lose the last
commits on power loss; OFF leaves it to the OS. See docs/operations-guide.md.

Retention: rows older than analytics_retention_days are deleted at start and
then daily, so the database stays bounded.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import sqlite3
import threading
import time
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

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
CREATE TABLE IF NOT EXISTS audit (
    seq INTEGER PRIMARY KEY AUTOINCREMENT, time REAL NOT NULL, principal TEXT NOT NULL,
    address TEXT NOT NULL, action TEXT NOT NULL, outcome TEXT NOT NULL, detail TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS audit_time ON audit(time);
CREATE INDEX IF NOT EXISTS events_time ON events(time);
CREATE INDEX IF NOT EXISTS transitions_time ON transitions(time);
CREATE INDEX IF NOT EXISTS operations_started ON operations(started_at);
CREATE INDEX IF NOT EXISTS errors_time ON errors(time);
CREATE INDEX IF NOT EXISTS recoveries_time ON recoveries(time);
"""

TABLES = {
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
    "audit": ("time", ["seq", "time", "principal", "address", "action", "outcome", "detail"]),
}
FILTERS = {  # which columns a query may filter on by equality, per table
    "events": ("type", "source", "outcome", "state"),
    "transitions": ("old_state", "new_state", "event", "event_id"),
    "operations": ("kind", "outcome"),
    "errors": ("code", "component", "classification", "state"),
    "recoveries": ("run_id", "error_code"),
    "audit": ("principal", "address", "action", "outcome"),
}
BACKLOG_LIMIT = 20_000
DAY_S = 86_400.0
# Where an export page ends: the time column's value and the rowid of its last row.
Cursor = tuple[float, int]


@dataclass(frozen=True, slots=True)
class Record:
    """One SQL statement for the writer: `sql` with `params`."""

    sql: str
    params: tuple[Any, ...]


def _json(value: Any) -> str:
    return json.dumps(value, default=str, separators=(",", ":"))


class Journal:
    """Append-only cell records in SQLite, written by one thread with group commit."""

    def __init__(self, path: Path, *, synchronous: str = "FULL", retention_days: int = 90) -> None:
        self.path = path
        self.synchronous = synchronous
        self.retention_days = retention_days
        self._queue: deque[tuple[list[Record], asyncio.Future[None] | None]] = deque()
        self._wake = threading.Condition()
        self._stopping = False
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self.recovered_from: Path | None = None  # a damaged database kept aside at open
        self.written = 0
        self.last_error: str | None = None

    # --- lifecycle ---------------------------------------------------------

    def open(self) -> None:
        """Open (or create) the database; a damaged one is kept aside and a new one started."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._check(self.path)
        except sqlite3.DatabaseError as exc:
            aside = self.path.with_name(f"{self.path.name}.corrupt-{int(time.time())}")
            self.path.replace(aside)
            for suffix in ("-wal", "-shm"):
                Path(f"{self.path}{suffix}").unlink(missing_ok=True)
            self.recovered_from = aside
            log.error(
                "journal %s is damaged (%s); kept as %s, starting a new one", self.path, exc, aside
            )
        connection = self._connect()
        connection.executescript(SCHEMA)
        connection.commit()
        connection.close()
        self._prune()

    def _check(self, path: Path) -> None:
        if not path.exists():
            return
        connection = sqlite3.connect(path)
        try:
            result = connection.execute("PRAGMA quick_check").fetchone()
            if result is None or result[0] != "ok":
                raise sqlite3.DatabaseError(f"quick_check: {result}")
        finally:
            connection.close()

    def _connect(self) -> sqlite3.Connection:
        connection = sqlite3.connect(self.path, check_same_thread=False, timeout=30)
        connection.execute("PRAGMA journal_mode=WAL")
        connection.execute(f"PRAGMA synchronous={self.synchronous}")
        return connection

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._thread = threading.Thread(target=self._write_loop, name="journal-writer", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Write what is queued, then stop the writer."""
        with self._wake:
            self._stopping = True
            self._wake.notify()
        if self._thread is not None:
            self._thread.join(timeout=30)

    @property
    def backlog(self) -> int:
        return len(self._queue)

    # --- writing -----------------------------------------------------------

    def append(self, records: list[Record], *, durable: bool = True) -> asyncio.Future[None] | None:
        """Queue records for one transaction; the future resolves once committed."""
        future = None
        if durable and self._loop is not None:
            future = self._loop.create_future()
        with self._wake:
            self._queue.append((records, future))
            self._wake.notify()
        return future

    async def caught_up(self) -> None:
        """Wait until every record queued before this call is committed.

        Why: the records of a transition are queued as the worker decides it, so a
        client that has just seen ERROR on /state and then asks /history must find
        that transition there. Queries call this first (read-your-writes). A failed
        write is reported by the writer itself; the reader just reads what is there.
        """
        future = self.append([])
        if future is not None:
            with contextlib.suppress(Exception):
                await future

    def _write_loop(self) -> None:
        connection = self._connect()
        last_prune = time.monotonic()
        while True:
            with self._wake:
                while not self._queue and not self._stopping:
                    self._wake.wait(timeout=60)
                batch = list(self._queue)
                self._queue.clear()
                stopping = self._stopping
            if batch:
                self._write(connection, batch)
            if stopping and not self._queue:
                break
            if time.monotonic() - last_prune > DAY_S:
                last_prune = time.monotonic()
                self._prune(connection)
        connection.close()

    def _write(self, connection: sqlite3.Connection, batch: list[Any]) -> None:
        error: Exception | None = None
        try:
            with connection:
                for records, _ in batch:
                    for record in records:
                        connection.execute(record.sql, tuple(_clean(p) for p in record.params))
            self.written += sum(len(records) for records, _ in batch)
        except Exception as exc:  # never let the writer die: every waiting answer must come
            error = exc
            self.last_error = str(exc)
            log.critical("journal write failed: %s", exc)
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        for _, future in batch:
            if future is not None:
                loop.call_soon_threadsafe(_settle, future, error)

    def _prune(self, connection: sqlite3.Connection | None = None) -> None:
        own = connection is None
        connection = connection or self._connect()
        cutoff = time.time() - self.retention_days * DAY_S
        try:
            with connection:
                for table, (time_column, _) in TABLES.items():
                    connection.execute(f"DELETE FROM {table} WHERE {time_column} < ?", (cutoff,))
        except sqlite3.Error as exc:
            log.error("journal retention pruning failed: %s", exc)
        finally:
            if own:
                connection.close()

    # --- records -------------------------------------------------------------

    @staticmethod
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
        return Record(
            "INSERT OR REPLACE INTO events VALUES (?,?,?,?,?,?,?,?)",
            (event_id, at, type_, source, _json(data), outcome, message, state),
        )

    @staticmethod
    def transition(row: dict[str, Any]) -> Record:
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

    @staticmethod
    def operation_started(run_id: str, kind: str, at: float, params: dict[str, Any]) -> Record:
        return Record(
            "INSERT OR REPLACE INTO operations (run_id, kind, started_at, params) VALUES (?,?,?,?)",
            (run_id, kind, at, _json(params)),
        )

    @staticmethod
    def operation_progress(run_id: str, progress: dict[str, Any]) -> Record:
        return Record(
            "UPDATE operations SET progress = ? WHERE run_id = ?", (_json(progress), run_id)
        )

    @staticmethod
    def operation_ended(
        run_id: str, at: float, outcome: str, result: Any, error: str | None, workpieces: int
    ) -> Record:
        return Record(
            "UPDATE operations SET ended_at = ?, outcome = ?, result = ?, error = ?, "
            "workpieces = ? WHERE run_id = ? AND ended_at IS NULL",
            (at, outcome, _json(result), error, workpieces, run_id),
        )

    @staticmethod
    def error(
        at: float,
        code: str,
        message: str,
        component: str,
        classification: str,
        event_id: str,
        state: str,
    ) -> Record:
        return Record(
            "INSERT INTO errors (time, code, message, component, classification, event_id, "
            "state) VALUES (?,?,?,?,?,?,?)",
            (at, code, message, component, classification, event_id, state),
        )

    @staticmethod
    def recovery(at: float, run_id: str, error_code: str, attempt: int, succeeded: bool) -> Record:
        return Record(
            "INSERT INTO recoveries (time, run_id, error_code, attempt, succeeded) "
            "VALUES (?,?,?,?,?)",
            (at, run_id, error_code, attempt, int(succeeded)),
        )

    @staticmethod
    def audit(
        at: float, principal: str, address: str, action: str, outcome: str, detail: str
    ) -> Record:
        return Record(
            "INSERT INTO audit (time, principal, address, action, outcome, detail) "
            "VALUES (?,?,?,?,?,?)",
            (at, principal, address, action, outcome, detail),
        )

    # --- reading (from a thread: these block) --------------------------------

    def query(
        self,
        table: str,
        *,
        since: float | None = None,
        until: float | None = None,
        filters: dict[str, str] | None = None,
        limit: int = 100,
        offset: int = 0,
        newest_first: bool = True,
    ) -> list[dict[str, Any]]:
        """Rows of `table` in a time range with equality filters, paged."""
        time_column, columns = TABLES[table]
        where, params = self._where(table, time_column, since, until, filters)
        order = "DESC" if newest_first else "ASC"
        sql = (
            f"SELECT {', '.join(columns)} FROM {table}{where} "
            f"ORDER BY {time_column} {order} LIMIT ? OFFSET ?"
        )
        with self._reader() as connection:
            rows = connection.execute(sql, (*params, limit, offset)).fetchall()
        return [dict(zip(columns, row, strict=True)) for row in rows]

    def count(
        self,
        table: str,
        *,
        since: float | None = None,
        until: float | None = None,
        filters: dict[str, str] | None = None,
    ) -> int:
        time_column, _ = TABLES[table]
        where, params = self._where(table, time_column, since, until, filters)
        with self._reader() as connection:
            return int(
                connection.execute(f"SELECT COUNT(*) FROM {table}{where}", params).fetchone()[0]
            )

    def last_rowid(self, table: str) -> int:
        """The largest rowid in `table` now (0 when empty): the snapshot bound of an export.

        Why the rowid: every table here is a rowid table, and a row inserted later gets
        a larger rowid (the AUTOINCREMENT tables never reuse one; `events` and
        `operations` take the largest + 1). So `rowid <= bound` keeps every row
        committed before the bound was read and leaves out the rows added while a long
        export streams, which would otherwise chase a table that keeps growing.
        """
        if table not in TABLES:  # only known tables are ever named in SQL
            raise ValueError(f"no table {table!r}")
        with self._reader() as connection:
            return int(connection.execute(f"SELECT MAX(rowid) FROM {table}").fetchone()[0] or 0)

    def page_after(
        self,
        table: str,
        *,
        since: float | None = None,
        until: float | None = None,
        filters: dict[str, str] | None = None,
        after: Cursor | None = None,
        bound: int,
        limit: int,
    ) -> tuple[list[tuple[Any, ...]], Cursor | None]:
        """One page of an export: rows oldest first, strictly after `after`, rowid <= `bound`.

        Keyset pagination on (time column, rowid): a page starts right after the last
        row of the previous one, so rows with equal times are neither repeated nor
        skipped, and every page costs the same however deep into the table it is
        (OFFSET would read and drop every earlier row, and shift when retention deletes
        old rows meanwhile). The time index holds that order already: SQLite keeps the
        rowid in each index entry. A fresh connection per page means no read
        transaction stays open while a slow client downloads, which would stop the WAL
        from being checkpointed.

        Returns the rows (the table's columns, in the order of TABLES) and the cursor
        to pass as `after` for the next page (None when the page is empty).
        """
        time_column, columns = TABLES[table]
        where, params = self._where(table, time_column, since, until, filters)
        clauses = [where or " WHERE 1", "rowid <= ?"]
        params = (*params, bound)
        if after is not None:
            clauses.append(f"({time_column}, rowid) > (?, ?)")
            params = (*params, *after)
        sql = (
            f"SELECT {', '.join(columns)}, {time_column}, rowid FROM {table}"
            f"{' AND '.join(clauses)} ORDER BY {time_column}, rowid LIMIT ?"
        )
        with self._reader() as connection:
            rows = connection.execute(sql, (*params, limit)).fetchall()
        if not rows:
            return [], None
        last = rows[-1]
        return [row[:-2] for row in rows], (last[-2], last[-1])

    def unfinished_operations(self) -> list[dict[str, Any]]:
        """Operations that started and never ended: the server stopped during them."""
        _, columns = TABLES["operations"]
        with self._reader() as connection:
            rows = connection.execute(
                f"SELECT {', '.join(columns)} FROM operations WHERE ended_at IS NULL "
                "ORDER BY started_at"
            ).fetchall()
        return [dict(zip(columns, row, strict=True)) for row in rows]

    def mark_interrupted(self, run_ids: Iterable[str], at: float) -> None:
        """Close the rows of operations a restart found unfinished (synchronously)."""
        with self._reader() as connection, connection:
            for run_id in run_ids:
                connection.execute(
                    "UPDATE operations SET ended_at = ?, outcome = 'interrupted', "
                    "error = 'the server stopped during the operation' "
                    "WHERE run_id = ? AND ended_at IS NULL",
                    (at, run_id),
                )

    def _where(
        self,
        table: str,
        time_column: str,
        since: float | None,
        until: float | None,
        filters: dict[str, str] | None,
    ) -> tuple[str, tuple[Any, ...]]:
        clauses, params = [], []
        if since is not None:
            clauses.append(f"{time_column} >= ?")
            params.append(since)
        if until is not None:
            clauses.append(f"{time_column} < ?")
            params.append(until)
        for column, value in (filters or {}).items():
            if column not in FILTERS[table]:
                raise ValueError(f"{table} cannot be filtered by {column!r}")
            clauses.append(f"{column} = ?")
            params.append(value)
        return (" WHERE " + " AND ".join(clauses)) if clauses else "", tuple(params)

    def _reader(self) -> sqlite3.Connection:
        connection = sqlite3.connect(self.path, timeout=30)
        connection.execute("PRAGMA journal_mode=WAL")
        return _Closing(connection)  # type: ignore[return-value]


class _Closing:
    """A connection used in a `with` block that is closed afterwards."""

    def __init__(self, connection: sqlite3.Connection) -> None:
        self.connection = connection

    def __enter__(self) -> sqlite3.Connection:
        return self.connection

    def __exit__(self, *exc_info: object) -> None:
        self.connection.close()


def _clean(value: Any) -> Any:
    """Text as SQLite can store it: unpaired surrogates (e.g. from a device) replaced."""
    if isinstance(value, str):
        return value.encode("utf-8", "replace").decode("utf-8")
    return value


def _settle(future: asyncio.Future[None], error: Exception | None) -> None:
    if future.done():
        return
    if error is None:
        future.set_result(None)
    else:
        future.set_exception(error)
