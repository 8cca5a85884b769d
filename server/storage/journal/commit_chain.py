"""The journal's commit chain: every commit numbered, its rows digested, the last one noted.

Why: SQLite drops every WAL frame from the first one whose checksum fails, so
damage to `journal.db-wal` shows up as rows that are simply not there; and a
byte changed inside a row passes PRAGMA quick_check. Neither is visible in the
tables themselves. So each transaction the writer commits also writes one row
of `commits`:

- `seq`: 1, 2, 3, ... with no gaps (retention removes only the oldest);
- `rows`: how many rows have been appended to each sealed table so far
  (cumulative, so a missing range says how many rows of which table it held);
- `digest`: of the previous commit's digest, this commit's number, time and
  counts, and every sealed row it appended, read back as SQLite stored it
  (each such row carries `commit_seq`, so the rows of a commit can be found
  and digested again, and read back the same way).

After the commit, the same facts are written to a small file beside the journal
(`<journal>.last-commit`), outside the database: a journal whose last commits
went with a damaged or lost WAL still has a gap to show, between its last
readable commit and the one this file names. The file is rewritten in place
after every commit without an fsync (a few microseconds): a killed process
leaves it current, and after a power cut it can only lag behind a journal whose
commits were fsynced (journal_synchronous FULL), which is no false alarm; with
NORMAL or OFF a power cut that loses the last commits is reported as what it
is. `verify.py` checks all this at start-up.

The digest guards against damage, not against someone who can rewrite the files.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import sqlite3
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from server.storage.journal.records import Record
from server.storage.journal.schema import column_names, sealed_form

log = logging.getLogger(__name__)

LAST_COMMIT_SUFFIX = ".last-commit"
LAST_COMMIT_SIZE = 512  # bytes; the file is padded to at least this, so it never shrinks


@dataclass(frozen=True, slots=True)
class Head:
    """A commit as the chain knows it: number, time, cumulative rows per table, digest."""

    seq: int
    time: float
    rows: dict[str, int]
    digest: str

    def as_json(self) -> str:
        return (
            f'{{"digest":"{self.digest}","rows":{rows_json(self.rows)},'
            f'"seq":{self.seq:d},"time":{self.time!r}}}'
        )

    @classmethod
    def from_json(cls, text: str) -> Head:
        """The head written by `as_json`; ValueError when `text` is not one."""
        try:
            document = json.loads(text)
            rows = {str(table): int(n) for table, n in dict(document["rows"]).items()}
            return cls(int(document["seq"]), float(document["time"]), rows, str(document["digest"]))
        except (TypeError, KeyError, AttributeError, ValueError) as exc:
            raise ValueError(f"not a commit record: {exc}") from exc


GENESIS = Head(0, 0.0, {}, "")
COMMIT_COLUMNS = "seq, time, rows, digest"  # a row of `commits`, as `head_of` reads it


def head_of(row: Sequence[Any]) -> Head:
    """The head a row of `commits` (COMMIT_COLUMNS) describes; ValueError when unreadable."""
    seq, at, rows, commit_digest = row
    try:
        counts = {str(table): int(n) for table, n in dict(json.loads(rows)).items()}
    except (TypeError, ValueError) as exc:
        raise ValueError(f"commit {seq}: its row counts are unreadable ({exc})") from exc
    return Head(int(seq), float(at), counts, str(commit_digest))


@dataclass(slots=True)
class Appended:
    """The sealed rows one commit appends, per table, in the order written."""

    rows: dict[str, list[tuple[Any, ...]]] = field(default_factory=dict)

    def add(self, table: str, row: tuple[Any, ...]) -> None:
        self.rows.setdefault(table, []).append(row)

    def count(self, table: str) -> int:
        return len(self.rows.get(table, ()))


def rows_json(rows: dict[str, int]) -> str:
    """The `rows` column: cumulative counts per table, canonical JSON (the table names
    are the journal's own, so they need no escaping; spelt out, as it is per commit)."""
    return "{" + ",".join(f'"{table}":{rows[table]:d}' for table in sorted(rows)) + "}"


def digest(previous: str, seq: int, at: float, rows: str, appended: Appended) -> str:
    """The chained digest of one commit (tables in name order, rows in the order written)."""
    h = hashlib.blake2b(digest_size=16)
    h.update(f"{previous}|{seq}|{at!r}|{rows}".encode())
    for table in sorted(appended.rows):
        h.update(repr((table, appended.rows[table])).encode("utf-8", "surrogatepass"))
    return h.hexdigest()


def cumulative(before: dict[str, int], appended: Appended) -> dict[str, int]:
    """The counts after a commit: `before` plus what it appended."""
    after = dict(before)
    for table, rows in appended.rows.items():
        after[table] = after.get(table, 0) + len(rows)
    return after


class LastCommitFile:
    """`<journal>.last-commit`: the head of the chain, outside the database.

    Written only by the writer thread, in place (one pwrite, no rename, no fsync).
    """

    def __init__(self, journal: Path) -> None:
        self.path = journal.with_name(journal.name + LAST_COMMIT_SUFFIX)
        self._fd: int | None = None
        self._size = LAST_COMMIT_SIZE

    def read(self) -> Head | None:
        """The head last written; None when there is no file; ValueError when unreadable."""
        try:
            text = self.path.read_bytes().decode("utf-8")
        except FileNotFoundError:
            return None
        except UnicodeDecodeError as exc:
            raise ValueError(f"not text: {exc}") from exc
        return Head.from_json(text)

    def write(self, head: Head) -> None:
        if self._fd is None:
            self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
            self._size = max(self._size, os.fstat(self._fd).st_size)
        data = (head.as_json() + "\n").encode()  # hex, digits and names: ASCII
        self._size = max(self._size, len(data))
        os.pwrite(self._fd, data.ljust(self._size, b" "), 0)

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


class CommitChain:
    """The writer's side: numbers and digests each commit, then notes it outside the database.

    `write` runs inside the writer's transaction and returns the new head;
    `committed` is called once that transaction is committed. A transaction
    that fails leaves the chain where it was.
    """

    def __init__(self, head: Head, last_commit: LastCommitFile) -> None:
        self.head = head
        self._last_commit = last_commit
        self._noting_failed = False  # logged once until a note succeeds again

    def write(
        self, connection: sqlite3.Connection, records: Iterable[Record], at: float
    ) -> Head | None:
        """Execute `records`, then the commit's own row; None when there was nothing to write."""
        seq = self.head.seq + 1
        first: dict[str, int] = {}  # the rowid of each sealed table's first new row
        written = 0
        for record in records:
            params = tuple(_clean(p) for p in record.params)
            written += 1
            if record.sealed is None:
                connection.execute(record.sql, params)
                continue
            cursor = connection.execute(record.sealed.sql, (*params, seq))
            if record.sealed.table not in first and cursor.lastrowid is not None:
                first[record.sealed.table] = cursor.lastrowid
        appended = Appended()
        for table, rowid in first.items():
            # Read back as verification will: the values SQLite stored, in rowid order
            # (a later row gets a larger rowid, and this thread is the only writer).
            appended.rows[table] = [
                sealed_form(table, row)
                for row in connection.execute(
                    f"SELECT {', '.join(column_names(table))} FROM {table} WHERE rowid >= ? "
                    "ORDER BY rowid",
                    (rowid,),
                )
            ]
        if not written:
            return None
        rows = cumulative(self.head.rows, appended)
        counts = rows_json(rows)
        head = Head(seq, at, rows, digest(self.head.digest, seq, at, counts, appended))
        connection.execute(
            "INSERT INTO commits (seq, time, rows, digest) VALUES (?,?,?,?)",
            (seq, at, counts, head.digest),
        )
        return head

    def committed(self, head: Head) -> None:
        """The transaction holding `head` is on disk: advance, and say so beside the journal."""
        self.head = head
        try:
            self._last_commit.write(head)
        except OSError as exc:  # the commit itself is on disk: never fail it for this
            if not self._noting_failed:
                log.error(
                    "could not note the journal's last commit in %s (%s): a journal cut "
                    "short would not be noticed at the next start",
                    self._last_commit.path,
                    exc,
                )
            self._noting_failed = True
        else:
            self._noting_failed = False

    def close(self) -> None:
        self._last_commit.close()


def _clean(value: Any) -> Any:
    """Text as SQLite can store it: unpaired surrogates (e.g. from a device) replaced."""
    if isinstance(value, str):
        return value.encode("utf-8", "replace").decode("utf-8")
    return value
