"""The journal: every event, transition, operation and error, in SQLite, durably.

- `schema`: the tables, their columns, and each table's equality filters;
- `records`: one function per kind of row, each returning a `Record`;
- `writer`: the writer thread (group commit; a future per append, resolved once
  committed: see there why), retention;
- `reader`: queries, counts, export pages, and the restart's view of
  unfinished operations.

Durability is the `journal_synchronous` setting (SQLite PRAGMA synchronous in
WAL mode): FULL (default) fsyncs the WAL at every commit and survives power
loss; NORMAL survives a crash of the server process but may lose the last
commits on power loss; OFF leaves it to the OS. See docs/operations-guide.md.

Retention: rows older than analytics_retention_days are deleted at open and
then daily, so the database stays bounded.
"""

from __future__ import annotations

import asyncio
import logging
import sqlite3
import time
from pathlib import Path

from server.storage.journal import records
from server.storage.journal.reader import Cursor, Reader
from server.storage.journal.records import Record
from server.storage.journal.schema import FILTERS, SCHEMA, TABLES, Filter, filter_columns
from server.storage.journal.writer import WriteFailure, Writer, prune
from server.storage.permissions import private_file

__all__ = [
    "FILTERS",
    "SCHEMA",
    "TABLES",
    "Cursor",
    "Filter",
    "Journal",
    "Record",
    "WriteFailure",
    "filter_columns",
    "records",
]

log = logging.getLogger(__name__)


class Journal(Reader):
    """Append-only cell records in SQLite, written by one thread with group commit.

    The reads (`query`, `count`, `last_rowid`, `page_after`,
    `unfinished_operations`, `mark_interrupted`) come from `Reader` and block:
    call them from a thread.
    """

    def __init__(self, path: Path, *, synchronous: str = "FULL", retention_days: int = 90) -> None:
        super().__init__(path)
        self.synchronous = synchronous
        self.retention_days = retention_days
        # `self._connect` is looked up here, so a subclass's override serves the writer.
        self._writer = Writer(self._connect, self._prune)

    # --- lifecycle ---------------------------------------------------------

    def open(self) -> None:
        """Open (or create) the database; a damaged one is kept aside and a new one started."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            _check(self.path)
        except sqlite3.DatabaseError as exc:
            aside = self.path.with_name(f"{self.path.name}.corrupt-{int(time.time())}")
            self.path.replace(aside)
            for suffix in ("-wal", "-shm"):
                Path(f"{self.path}{suffix}").unlink(missing_ok=True)
            log.error(
                "journal %s is damaged (%s); kept as %s, starting a new one", self.path, exc, aside
            )
        private_file(self.path)  # 0600 before SQLite opens it; its -wal and -shm take its mode
        connection = self._connect()
        connection.executescript(SCHEMA)
        connection.commit()
        connection.close()
        connection = self._connect()
        try:
            self._prune(connection)
        finally:
            connection.close()

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        """Start the writer thread; append's futures resolve on `loop`."""
        self._writer.start(loop)

    def stop(self) -> None:
        """Write what is queued, then stop the writer."""
        self._writer.stop()

    @property
    def backlog(self) -> int:
        """Appends queued and not yet taken by the writer."""
        return self._writer.backlog

    @property
    def last_error(self) -> WriteFailure | None:
        """The last write failure (message, Unix time); None once a write succeeds."""
        return self._writer.last_error

    # --- writing -----------------------------------------------------------

    def append(self, records: list[Record], *, durable: bool = True) -> asyncio.Future[None] | None:
        """Queue records for one transaction; the future resolves once committed
        (None when not `durable`, or before `start`)."""
        return self._writer.append(records, durable=durable)

    async def caught_up(self) -> None:
        """Wait until every record queued before this call is committed (read-your-writes)."""
        await self._writer.caught_up()

    # --- connections -------------------------------------------------------

    def _connect(self) -> sqlite3.Connection:
        """A connection for writing (the writer's, and at open)."""
        connection = sqlite3.connect(self.path, check_same_thread=False, timeout=30)
        connection.execute("PRAGMA journal_mode=WAL")
        connection.execute(f"PRAGMA synchronous={self.synchronous}")
        return connection

    def _prune(self, connection: sqlite3.Connection) -> None:
        prune(connection, self.retention_days)


def _check(path: Path) -> None:
    """Raise sqlite3.DatabaseError when the database at `path` is damaged."""
    if not path.exists():
        return
    connection = sqlite3.connect(path)
    try:
        result = connection.execute("PRAGMA quick_check").fetchone()
        if result is None or result[0] != "ok":
            raise sqlite3.DatabaseError(f"quick_check: {result}")
    finally:
        connection.close()
