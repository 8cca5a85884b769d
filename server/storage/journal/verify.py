"""Start-up's check of the journal: is every commit there, and are its rows what was written?

What it can tell, from the commit chain (`commit_chain.py`):

- commits missing at the end: the last-commit file names a later commit than
  the journal's last one (a damaged or lost WAL: SQLite drops every frame from
  the first bad one, silently);
- commits missing in between: a gap in `commits.seq` (the oldest are removed
  only by retention, which notes where it cut in `journal_meta`);
- rows missing or rewritten: the rows a commit appended, digested again, do not
  give its digest (the newest `window` commits), or a table holds fewer rows
  than its commits appended (every commit, counted in SQL).

It only reads, on the caller's connection: deciding what to do is
`inspection.py`'s. Bounded at start-up: the counts are one pass of SQLite over
each table, the digests cover only the newest `window` commits (`python -m
bench.journal_verify` measures both on a journal of a million rows); `python -m
server.storage.journal.check <journal.db>` digests every commit, on demand.
"""

from __future__ import annotations

import sqlite3
import time
from dataclasses import dataclass, field
from typing import Any

from server.storage.journal.commit_chain import (
    COMMIT_COLUMNS,
    GENESIS,
    Appended,
    Head,
    digest,
    head_of,
    rows_json,
)
from server.storage.journal.later_columns import stored_columns
from server.storage.journal.schema import COMMIT_SEQ, SEALED, sealed_form

WINDOW = 10_000  # the newest commits whose rows start-up digests again


@dataclass(frozen=True, slots=True)
class Damage:
    """One thing found wrong with the journal, in words a technician can act on."""

    message: str
    first_commit: int | None = None
    last_commit: int | None = None
    missing_rows: dict[str, int] = field(default_factory=dict)  # table -> rows lost
    kept_as: str | None = None  # the file the damaged journal was set aside or copied to
    found_at: float = 0.0  # Unix time

    def as_dict(self) -> dict[str, Any]:
        return {
            "message": self.message,
            "first_commit": self.first_commit,
            "last_commit": self.last_commit,
            "missing_rows": dict(self.missing_rows),
            "kept_as": self.kept_as,
            "found_at": self.found_at,
        }


@dataclass(frozen=True, slots=True)
class Verdict:
    """Where the chain goes on (the last readable commit), and what was found wrong."""

    head: Head
    damage: list[Damage]
    digested: int  # commits whose rows were digested again


def verify(
    connection: sqlite3.Connection, noted: Head | None, *, window: int | None = WINDOW
) -> Verdict:
    """Check the journal on `connection` against itself and against `noted`, the head the
    last-commit file names (None: no file). `window`: how many of the newest commits to
    digest again (None: all). Raises sqlite3.DatabaseError when SQLite cannot read it."""
    has_chain = connection.execute(
        "SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'commits'"
    ).fetchone()
    if not has_chain:  # a new journal, or one from before the chain
        return Verdict(GENESIS, _cut_short(GENESIS, noted, {}), 0)
    anchor = _anchor(connection)
    last = connection.execute(
        f"SELECT {COMMIT_COLUMNS} FROM commits ORDER BY seq DESC LIMIT 1"
    ).fetchone()
    head = anchor if last is None or int(last[0]) <= anchor.seq else head_of(last)
    damage = _gaps(connection, anchor, head)
    start = anchor.seq + 1 if window is None else max(anchor.seq + 1, head.seq - window + 1)
    rows, beyond = _rows_from(connection, start, head.seq)
    damage += _cut_short(head, noted, beyond)
    damage += _not_as_noted(connection, anchor, head, noted)
    damage += _digests(connection, anchor, head, start, rows)
    if not damage:
        damage += _counts(connection, anchor, head)
    return Verdict(head, damage, max(0, head.seq - start + 1))


def _anchor(connection: sqlite3.Connection) -> Head:
    """Where the chain starts: where retention last cut it, or where it was started
    again after it could not be read (GENESIS when neither happened)."""
    has_meta = connection.execute(
        "SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'journal_meta'"
    ).fetchone()
    if not has_meta:
        return GENESIS
    found = connection.execute(
        "SELECT value FROM journal_meta WHERE key = 'chain_start'"
    ).fetchone()
    return GENESIS if found is None else Head.from_json(str(found[0]))


def _commits(first: int, last: int) -> str:
    return f"commit {first}" if first == last else f"commits {first} to {last}"


def _rows(counts: dict[str, int]) -> str:
    """E.g. "rows of audit 2, events 6, transitions 6"."""
    named = ", ".join(f"{table} {n}" for table, n in sorted(counts.items()) if n)
    return f"rows of {named}" if named else "no rows"


def _difference(after: dict[str, int], before: dict[str, int]) -> dict[str, int]:
    tables = set(after) | set(before)
    found = {t: after.get(t, 0) - before.get(t, 0) for t in tables}
    return {t: n for t, n in sorted(found.items()) if n > 0}


def _cut_short(head: Head, noted: Head | None, beyond: dict[str, int]) -> list[Damage]:
    """The commits after `head` that the last-commit file says were made."""
    if noted is None or noted.seq <= head.seq:
        return []
    first, last = head.seq + 1, noted.seq
    lost = {t: n - beyond.get(t, 0) for t, n in _difference(noted.rows, head.rows).items()}
    lost = {t: n for t, n in lost.items() if n > 0}
    if first == last:
        what = f"its last commit ({first}, made {_local(noted.time)}) is missing, with its"
    else:
        what = (
            f"its last {last - first + 1} commits ({first} to {last}, made until "
            f"{_local(noted.time)}) are missing, with their"
        )
    return [
        Damage(
            f"journal damaged: {what} {_rows(lost)}. SQLite drops without a word "
            "whatever follows a damaged frame of journal.db-wal, or a lost one",
            first,
            last,
            lost,
        )
    ]


def _local(at: float) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(at))


def _not_as_noted(
    connection: sqlite3.Connection, anchor: Head, head: Head, noted: Head | None
) -> list[Damage]:
    """The commit the last-commit file names, found different in the journal."""
    if noted is None or not anchor.seq < noted.seq <= head.seq:
        return []
    row = connection.execute(
        f"SELECT {COMMIT_COLUMNS} FROM commits WHERE seq = ?", (noted.seq,)
    ).fetchone()
    if row is None or head_of(row).digest == noted.digest:
        return []  # a missing commit is a gap, reported as such
    return [
        Damage(
            f"journal damaged: commit {noted.seq} is not the one last written (its "
            "digest differs from the last-commit record's): rewritten",
            noted.seq,
            noted.seq,
        )
    ]


def _gaps(connection: sqlite3.Connection, anchor: Head, head: Head) -> list[Damage]:
    """Ranges of commits missing between the anchor and the head."""
    count, lowest = connection.execute(
        "SELECT COUNT(*), MIN(seq) FROM commits WHERE seq > ?", (anchor.seq,)
    ).fetchone()
    if count == head.seq - anchor.seq:
        return []
    ranges: list[tuple[int, int]] = []
    if lowest is not None and lowest > anchor.seq + 1:
        ranges.append((anchor.seq + 1, int(lowest) - 1))
    ranges += [
        (int(seq) + 1, int(following) - 1)
        for seq, following in connection.execute(
            "SELECT seq, following FROM (SELECT seq, LEAD(seq) OVER (ORDER BY seq) AS "
            "following FROM commits WHERE seq > ?) WHERE following > seq + 1",
            (anchor.seq,),
        )
    ]
    found = []
    for first, last in ranges:
        # The neighbours of a gap exist: the anchor or a commit before, a commit after.
        before = _head_at(connection, first - 1, anchor) or anchor
        after = _head_at(connection, last + 1, anchor) or head
        own = _rows_of(connection, last + 1, last + 1)
        present = _rows_of(connection, first, last)
        expected = _difference(_difference(after.rows, own), before.rows)
        lost = {t: n - present.get(t, 0) for t, n in expected.items() if n > present.get(t, 0)}
        found.append(
            Damage(
                f"journal damaged: {_commits(first, last)} of {head.seq} "
                f"{'is' if first == last else 'are'} missing, with their {_rows(lost)}",
                first,
                last,
                lost,
            )
        )
    return found


def _head_at(connection: sqlite3.Connection, seq: int, anchor: Head) -> Head | None:
    if seq == anchor.seq:
        return anchor
    row = connection.execute(
        f"SELECT {COMMIT_COLUMNS} FROM commits WHERE seq = ?", (seq,)
    ).fetchone()
    return None if row is None else head_of(row)


def _rows_of(connection: sqlite3.Connection, first: int, last: int) -> dict[str, int]:
    """Rows per sealed table appended by commits `first` to `last` (a pass over each table)."""
    return {
        table: int(
            connection.execute(
                f"SELECT COUNT(*) FROM {table} WHERE {COMMIT_SEQ} BETWEEN ? AND ?", (first, last)
            ).fetchone()[0]
        )
        for table in SEALED
    }


def _rows_from(
    connection: sqlite3.Connection, start: int, last: int
) -> tuple[dict[int, Appended], dict[str, int]]:
    """The sealed rows of commits `start` to `last`, per commit, in the order written.

    Only the rows after the last one of an older commit are read (a row appended
    later has a larger rowid; SQLite finds that one scanning from the end), so
    the cost follows the window, not the table. Rows written without a commit
    (by hand, or before the chain) are no commit's. Also returns, per table, how
    many rows name a commit after `last`, one the journal does not have.
    """
    found: dict[int, Appended] = {}
    beyond: dict[str, int] = {}
    for table in SEALED:
        older = connection.execute(
            f"SELECT rowid FROM {table} WHERE {COMMIT_SEQ} < ? ORDER BY rowid DESC LIMIT 1",
            (start,),
        ).fetchone()
        rows = connection.execute(
            f"SELECT {COMMIT_SEQ}, {stored_columns(connection, table)} FROM {table} "
            f"WHERE rowid > ? AND {COMMIT_SEQ} IS NOT NULL ORDER BY rowid",
            (older[0] if older else 0,),
        )
        for row in rows:
            seq = row[0]
            if seq > last:
                beyond[table] = beyond.get(table, 0) + 1
            else:  # the row as the writer read it back: a tuple of TABLES' columns
                found.setdefault(int(seq), Appended()).add(table, sealed_form(table, row[1:]))
    return found, beyond


def _digests(
    connection: sqlite3.Connection,
    anchor: Head,
    head: Head,
    start: int,
    rows: dict[int, Appended],
) -> list[Damage]:
    """The commits from `start` whose rows no longer give their digest, in ranges.

    Each commit is digested from the previous one's stored digest, so one bad
    commit is one finding, not every commit after it.
    """
    stored: dict[int, tuple[float, str, str]] = {
        int(seq): (float(at), str(counts), str(commit_digest))
        for seq, at, counts, commit_digest in connection.execute(
            f"SELECT {COMMIT_COLUMNS} FROM commits WHERE seq >= ? ORDER BY seq", (start - 1,)
        )
    }
    stored[anchor.seq] = (anchor.time, rows_json(anchor.rows), anchor.digest)
    bad: list[tuple[int, dict[str, int], list[str]]] = []
    for seq in range(start, head.seq + 1):
        commit, previous = stored.get(seq), stored.get(seq - 1)
        if commit is None or previous is None:
            continue  # a gap: reported as missing commits
        at, counts, commit_digest = commit
        appended = rows.get(seq, Appended())
        if digest(previous[2], seq, at, counts, appended) == commit_digest:
            continue
        try:
            expected = _difference(head_of((seq, *commit)).rows, head_of((seq - 1, *previous)).rows)
        except ValueError:  # its counts are what was rewritten
            expected = {}
        lost = {t: n - appended.count(t) for t, n in expected.items() if n > appended.count(t)}
        bad.append((seq, lost, sorted(set(expected) | set(appended.rows))))
    return [_rewritten(run) for run in _runs(bad)]


def _runs(
    bad: list[tuple[int, dict[str, int], list[str]]],
) -> list[list[tuple[int, dict[str, int], list[str]]]]:
    """Consecutive commits together."""
    runs: list[list[tuple[int, dict[str, int], list[str]]]] = []
    for item in bad:
        if runs and runs[-1][-1][0] == item[0] - 1:
            runs[-1].append(item)
        else:
            runs.append([item])
    return runs


def _rewritten(run: list[tuple[int, dict[str, int], list[str]]]) -> Damage:
    first, last = run[0][0], run[-1][0]
    lost: dict[str, int] = {}
    tables: set[str] = set()
    for _, missing, named in run:
        for table, n in missing.items():
            lost[table] = lost.get(table, 0) + n
        tables.update(named)
    what = f"{_rows(lost)} missing" if lost else "rewritten"
    return Damage(
        f"journal damaged: the rows of {_commits(first, last)} in "
        f"{', '.join(sorted(tables))} do not match the digest made when written: {what}",
        first,
        last,
        lost,
    )


def _counts(connection: sqlite3.Connection, anchor: Head, head: Head) -> list[Damage]:
    """Each sealed table's rows against what its commits appended (one pass each, in SQL)."""
    expected = _difference(head.rows, anchor.rows)
    present = _rows_of(connection, anchor.seq + 1, head.seq)
    lost = {t: n - present.get(t, 0) for t, n in expected.items() if n > present.get(t, 0)}
    if not lost:
        return []
    return [
        Damage(
            f"journal damaged: {_rows(lost)} appended by {_commits(anchor.seq + 1, head.seq)} "
            "missing (python -m server.storage.journal.check names the commits)",
            anchor.seq + 1,
            head.seq,
            lost,
        )
    ]
