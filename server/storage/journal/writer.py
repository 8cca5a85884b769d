"""The journal's writer thread: group commit, answers after the commit, retention.

Why a writer thread with group commit: SQLite writes (and their fsync) must
never run on the event loop, and the worker must never wait for the disk. The
worker hands records to `append`, which returns a future; the writer thread
takes everything queued, writes it in one transaction, commits, then resolves
those futures. A command's HTTP answer waits for that future, so **an event the
API acknowledged is on disk when the acknowledgement leaves**, while the
worker goes on with the next event and a slow disk delays answers, never
decisions or the emergency stop.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import sqlite3
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from server.common.runtime import background_thread
from server.storage.journal.commit_chain import COMMIT_COLUMNS, CommitChain, Head, head_of
from server.storage.journal.records import Record
from server.storage.journal.schema import COMMIT_SEQ, SEALED, TABLES, time_column

log = logging.getLogger(__name__)

DAY_S = 86_400.0

Batch = list[tuple[list[Record], "asyncio.Future[None] | None"]]


@dataclass(frozen=True, slots=True)
class WriteFailure:
    """The journal's last failed write: what SQLite said, and when (Unix time)."""

    message: str
    at: float

    def as_dict(self) -> dict[str, Any]:
        return {"message": self.message, "at": self.at}


def prune(connection: sqlite3.Connection, retention_days: float) -> None:
    """Delete the rows older than `retention_days` from every table (errors logged).

    The commit chain is cut with them: the commits up to the last one that made
    a row now deleted (or made before the cutoff) go, and the last of those is
    kept in `journal_meta` as where the chain now starts; the rows of those
    commits that are younger stay, no longer checked. So start-up's
    verification never takes retention for damage.
    """
    cutoff = time.time() - retention_days * DAY_S
    try:
        with connection:
            cut = _chain_cut(connection, cutoff)
            for table in TABLES:
                column = time_column(table)
                connection.execute(f"DELETE FROM {table} WHERE {column} < ?", (cutoff,))
            if cut is not None:
                connection.execute("DELETE FROM commits WHERE seq <= ?", (cut.seq,))
                note_chain_start(connection, cut)
    except (sqlite3.Error, ValueError) as exc:  # ValueError: a commit row that does not read
        log.error("journal retention pruning failed: %s", exc)


def note_chain_start(connection: sqlite3.Connection, anchor: Head) -> None:
    """Where the commit chain now starts: verification checks only the commits after it."""
    connection.execute(
        "INSERT OR REPLACE INTO journal_meta (key, value) VALUES ('chain_start', ?)",
        (anchor.as_json(),),
    )


def _chain_cut(connection: sqlite3.Connection, cutoff: float) -> Head | None:
    """The last commit retention removes (None when none is to go): the later of the
    last one before the first made since `cutoff` and the last that made a row older
    than `cutoff` (a row's time is its own, so a clock set back can make them differ)."""
    first_kept = connection.execute(
        "SELECT seq FROM commits WHERE time >= ? ORDER BY seq LIMIT 1", (cutoff,)
    ).fetchone()
    last = connection.execute("SELECT MAX(seq) FROM commits").fetchone()[0]
    candidates = [last if first_kept is None else first_kept[0] - 1]
    for table in SEALED:
        candidates.append(
            connection.execute(
                f"SELECT MAX({COMMIT_SEQ}) FROM {table} WHERE {time_column(table)} < ?",
                (cutoff,),
            ).fetchone()[0]
        )
    through = max((int(c) for c in candidates if c is not None), default=0)
    start = connection.execute(
        "SELECT value FROM journal_meta WHERE key = 'chain_start'"
    ).fetchone()
    if start is not None and through <= Head.from_json(str(start[0])).seq:
        return None  # never back: the chain may have been started again after that
    row = connection.execute(
        f"SELECT {COMMIT_COLUMNS} FROM commits WHERE seq <= ? ORDER BY seq DESC LIMIT 1",
        (through,),
    ).fetchone()
    return None if row is None else head_of(row)


class Writer:
    """One thread writing queued records, a transaction per wake-up, pruning daily.

    `connect` opens the thread's connection (called on the thread); `prune` is
    given that connection once a day. Each transaction goes through the commit
    chain (`commit_chain.py`), which numbers it, digests its rows and notes it
    beside the journal once committed.
    """

    def __init__(
        self,
        connect: Callable[[], sqlite3.Connection],
        prune: Callable[[sqlite3.Connection], None],
        chain: CommitChain,
    ) -> None:
        self._connect = connect
        self._prune = prune
        self._queue: deque[tuple[list[Record], asyncio.Future[None] | None]] = deque()
        # Batches are numbered as queued; `_committed` is the number of the last one
        # written (seen on the loop), and `_waiting` the `caught_up` calls not yet met.
        self._queued = 0
        self._committed = 0
        self._waiting: list[tuple[int, asyncio.Future[None]]] = []
        self._wake = threading.Condition()
        self._stopping = False
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._chain = chain
        # The last write failure; None once a write succeeds (or when none failed).
        self.last_error: WriteFailure | None = None

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        """Start the thread; futures are resolved on `loop`."""
        self._loop = loop
        self._thread = threading.Thread(target=self._run, name="journal-writer", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Write what is queued, then stop the thread."""
        with self._wake:
            self._stopping = True
            self._wake.notify()
        if self._thread is not None:
            self._thread.join(timeout=30)

    @property
    def backlog(self) -> int:
        """Lists of records queued and not yet taken by the thread."""
        return len(self._queue)

    def append(self, records: list[Record], *, durable: bool = True) -> asyncio.Future[None] | None:
        """Queue records for one transaction; the future resolves once committed.

        No future when `durable` is False or before `start`.
        """
        future = None
        if durable and self._loop is not None:
            future = self._loop.create_future()
        with self._wake:
            self._queue.append((records, future))
            self._queued += 1
            self._wake.notify()
        return future

    async def caught_up(self) -> None:
        """Wait until every record queued before this call is committed.

        Why: the records of a transition are queued as the worker decides it, so a
        client that has just seen ERROR on /state and then asks /history must find
        that transition there. Queries call this first (read-your-writes). A failed
        write is reported by the writer itself; the reader just reads what is there.

        It queues nothing: it waits for the transaction that takes the last batch
        queued. The plant's interfaces wait here for every transition, at the
        moment its command is answered; a marker of their own made the writer
        thread take another turn (and wake the loop again) just then.
        """
        if self._loop is None or self._committed >= self._queued:
            return
        waiter = self._loop.create_future()
        self._waiting.append((self._queued, waiter))
        await waiter

    def _run(self) -> None:
        with background_thread():  # held back while an e-stop's frames are written
            self._write_until_stopped()

    def _write_until_stopped(self) -> None:
        connection = self._connect()
        last_prune = time.monotonic()
        while True:
            with self._wake:
                while not self._queue and not self._stopping:
                    self._wake.wait(timeout=60)
                batch = list(self._queue)
                self._queue.clear()
                through = self._queued  # the number of the last batch taken
                stopping = self._stopping
            if batch:
                self._write(connection, batch, through)
            if stopping and not self._queue:
                break
            if time.monotonic() - last_prune > DAY_S:
                last_prune = time.monotonic()
                self._prune(connection)
        connection.close()
        self._chain.close()

    def _write(self, connection: sqlite3.Connection, batch: Batch, through: int) -> None:
        error: Exception | None = None
        try:
            with connection:
                head = self._chain.write(
                    connection, (record for records, _ in batch for record in records), time.time()
                )
            if head is not None:  # not just read-your-writes markers
                self._chain.committed(head)
                self.last_error = None
        except Exception as exc:  # never let the writer die: every waiting answer must come
            error = exc
            self.last_error = WriteFailure(str(exc), time.time())
            log.critical("journal write failed: %s", exc)
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        futures = [future for _, future in batch if future is not None]
        with contextlib.suppress(RuntimeError):  # the loop closed meanwhile
            loop.call_soon_threadsafe(self._settle, futures, error, through)

    def _settle(
        self, futures: list[asyncio.Future[None]], error: Exception | None, through: int
    ) -> None:
        """On the loop, once per transaction: its answers, then the waits it meets."""
        for future in futures:
            if future.done():
                continue
            if error is None:
                future.set_result(None)
            else:
                future.set_exception(error)
        self._committed = through
        met = [waiter for number, waiter in self._waiting if number <= through]
        if met:
            self._waiting = [(n, w) for n, w in self._waiting if n > through]
            for waiter in met:
                if not waiter.done():
                    waiter.set_result(None)
