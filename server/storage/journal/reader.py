"""Reading the journal: pages, counts, export pages, and the restart's recovery.

Every call opens its own connection and closes it (these block: call them from
a thread), so no read transaction outlives a call and the WAL can always be
checkpointed.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from server.storage.journal.schema import TABLES, column_names, filter_columns, time_column

# Where an export page ends: the time column's value and the rowid of its last row.
Cursor = tuple[float, int]


class Reader:
    """Reads of the journal at `path`."""

    def __init__(self, path: Path) -> None:
        self.path = path

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
        time_column, columns = _columns(table)
        where, params = _where(table, time_column, since, until, filters)
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
        """How many rows `query` would find with no limit."""
        where, params = _where(table, time_column(table), since, until, filters)
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
        time_column, columns = _columns(table)
        where, params = _where(table, time_column, since, until, filters)
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
        columns = column_names("operations")
        with self._reader() as connection:
            rows = connection.execute(
                f"SELECT {', '.join(columns)} FROM operations WHERE ended_at IS NULL "
                "ORDER BY started_at"
            ).fetchall()
        return [dict(zip(columns, row, strict=True)) for row in rows]

    def row(self, table: str, seq: int) -> dict[str, Any] | None:
        """The row of `table` numbered `seq`, or None when there is none (pruned, or never)."""
        _, columns = _columns(table)
        with self._reader() as connection:
            found = connection.execute(
                f"SELECT {', '.join(columns)} FROM {table} WHERE seq = ?", (seq,)
            ).fetchone()
        return dict(zip(columns, found, strict=True)) if found else None

    def operation(self, run_id: str) -> dict[str, Any] | None:
        """The `operations` row of run `run_id`, or None when there is none (pruned, or never)."""
        columns = column_names("operations")
        with self._reader() as connection:
            found = connection.execute(
                f"SELECT {', '.join(columns)} FROM operations WHERE run_id = ?", (run_id,)
            ).fetchone()
        return dict(zip(columns, found, strict=True)) if found else None

    def faults_of(self, event_id: str) -> list[dict[str, Any]]:
        """The `errors` rows an event recorded (the fault that took the cell to ERROR)."""
        columns = column_names("errors")
        with self._reader() as connection:
            rows = connection.execute(
                f"SELECT {', '.join(columns)} FROM errors WHERE event_id = ? ORDER BY seq",
                (event_id,),
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

    def _reader(self) -> _Closing:
        connection = sqlite3.connect(self.path, timeout=30)
        connection.execute("PRAGMA journal_mode=WAL")
        return _Closing(connection)


def _columns(table: str) -> tuple[str, tuple[str, ...]]:
    """The time column of `table` and its columns, in the order rows are read."""
    return time_column(table), column_names(table)


def _where(
    table: str,
    time_column: str,
    since: float | None,
    until: float | None,
    filters: dict[str, str] | None,
) -> tuple[str, tuple[Any, ...]]:
    clauses: list[str] = []
    params: list[object] = []
    if since is not None:
        clauses.append(f"{time_column} >= ?")
        params.append(since)
    if until is not None:
        clauses.append(f"{time_column} < ?")
        params.append(until)
    allowed = filter_columns(table)
    for column, value in (filters or {}).items():
        if column not in allowed:  # only declared columns are ever named in SQL
            raise ValueError(f"{table} cannot be filtered by {column!r}")
        clauses.append(f"{column} = ?")
        params.append(value)
    return (" WHERE " + " AND ".join(clauses)) if clauses else "", tuple(params)


class _Closing:
    """A connection used in a `with` block that is closed afterwards."""

    def __init__(self, connection: sqlite3.Connection) -> None:
        self.connection = connection

    def __enter__(self) -> sqlite3.Connection:
        return self.connection

    def __exit__(self, *exc_info: object) -> None:
        self.connection.close()
