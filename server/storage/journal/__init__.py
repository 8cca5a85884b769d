"""The journal: every event, transition, operation and error, in SQLite, durably.

- `tables`: each table declared once (its columns with SQL and Python types and
  meanings, its time column, its filters), in the terms of `declaration`;
  `schema` derives the SQL, the filters and the rest from them;
- `records`: one function per kind of row, each returning a `Record` built
  from the table's declaration;
- `writer`: the writer thread (group commit; a future per append, resolved once
  committed: see there why), retention;
- `commit_chain`: each commit numbered, its rows digested, the last one noted
  beside the journal; `verify` checks that at start-up and `inspection` decides
  what to do with a damaged journal (kept readable, or set aside: see there);
  `check` is the same check by hand (`python -m server.storage.journal.check`);
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
import sqlite3
from pathlib import Path

from server.storage.journal import records
from server.storage.journal.commit_chain import GENESIS, CommitChain, LastCommitFile
from server.storage.journal.declaration import Column, Filter, Table
from server.storage.journal.inspection import inspect
from server.storage.journal.later_columns import add_commit_seq
from server.storage.journal.reader import Cursor, Reader
from server.storage.journal.records import Record
from server.storage.journal.schema import FILTERS, PART_FIGURES, SCHEMA, TABLES, filter_columns
from server.storage.journal.verify import Damage
from server.storage.journal.writer import WriteFailure, Writer, note_chain_start, prune
from server.storage.permissions import private_file

__all__ = [
    "FILTERS",
    "PART_FIGURES",
    "SCHEMA",
    "TABLES",
    "Column",
    "Cursor",
    "Damage",
    "Filter",
    "Journal",
    "Record",
    "Table",
    "WriteFailure",
    "filter_columns",
    "records",
]


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
        # What start-up found wrong with the journal (empty when nothing), for /health.
        self.damage: list[Damage] = []
        self._last_commit = LastCommitFile(path)
        self._chain = CommitChain(GENESIS, self._last_commit)
        # `self._connect` is looked up here, so a subclass's override serves the writer.
        self._writer = Writer(self._connect, self._prune, self._chain)

    # --- lifecycle ---------------------------------------------------------

    def open(self) -> None:
        """Open (or create) the database, checked first: damage is logged and kept in
        `damage`, never fatal (see `inspection.py` for what is done with the files)."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        found = inspect(self.path, self._last_commit)
        self.damage = found.damage
        self._chain.head = found.head
        private_file(self.path)  # 0600 before SQLite opens it; its -wal and -shm take its mode
        connection = self._connect()
        connection.executescript(SCHEMA)
        add_commit_seq(connection)
        if found.restarted:
            note_chain_start(connection, found.head)
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
