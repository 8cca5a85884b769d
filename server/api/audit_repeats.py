"""Identical refusals within a window are one audit row with a count.

Why: every refusal is on record, and a client that repeats one (3000 wrong
tokens in a few seconds) would write a row each: the journal would grow with
whatever an anonymous client chose to send. The first refusal of its kind (same
principal, address, action, outcome and reason) is written at once; the
identical ones that follow within `audit_repeat_window` are counted, and
written as one more row whose `count` says how many it stands for, at the time
of the last of them, when the window closes. A repetition that goes on keeps
folding, one row per window; once a window passes without one, the next is
written at once again. So the counts of a kind's rows add up to every refusal
made, and `GET /audit` (which writes what is pending first) never shows fewer
than were made.

Only refusals are folded: an accepted action is always its own row. The
journal's rows are sealed by the commit chain and never updated, which is why
the count goes into a row of its own rather than raising the first one's.
The table of kinds being folded is bounded (`MAX_KINDS`): past it a refusal
is simply written, one row each.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from dataclasses import dataclass

from server.storage.journal import Journal, Record, records

MAX_KINDS = 10_000  # kinds of refusal being folded at once

# principal, address, action, outcome, detail
Kind = tuple[str, str, str, str, str]
# A row to write: its kind, how many refusals it stands for, and the time of the last one.
Row = tuple[Kind, int, float]


@dataclass(slots=True)
class _Fold:
    window_ends: float
    repeats: int = 0  # folded since the last row of this kind
    last_at: float = 0.0


class RepeatFolder:
    """The pure part: which refusals to write now, and which rows the windows leave."""

    def __init__(self, window: float, max_kinds: int = MAX_KINDS) -> None:
        self.window = window
        self.max_kinds = max_kinds
        self._folds: dict[Kind, _Fold] = {}

    def offer(self, kind: Kind, at: float) -> list[Row]:
        """A refusal made at `at`: the rows to write now (none while it is being folded)."""
        fold = self._folds.get(kind)
        if fold is None:
            if len(self._folds) < self.max_kinds:
                self._folds[kind] = _Fold(at + self.window)
            return [(kind, 1, at)]
        if at < fold.window_ends:
            fold.repeats += 1
            fold.last_at = at
            return []
        # Its window is over and not yet swept: what it folded first, then this one.
        written = [(kind, fold.repeats, fold.last_at)] if fold.repeats else []
        if fold.repeats:  # still repeating: keep folding, from this one on
            fold.repeats, fold.last_at = 1, at
        else:
            written.append((kind, 1, at))
        fold.window_ends = at + self.window
        return written

    def due(self, now: float) -> list[Row]:
        """The rows of the windows closed by `now`; a kind whose window folded nothing is
        forgotten, one that folded some folds on for another window."""
        written: list[Row] = []
        for kind, fold in list(self._folds.items()):
            if fold.window_ends > now:
                continue
            if fold.repeats:
                written.append((kind, fold.repeats, fold.last_at))
                fold.repeats = 0
                fold.window_ends = now + self.window
            else:
                del self._folds[kind]
        return written

    def drain(self) -> list[Row]:
        """Every count folded so far, as rows (for a reader of the trail, or at shutdown)."""
        written: list[Row] = []
        for kind, fold in self._folds.items():
            if fold.repeats:
                written.append((kind, fold.repeats, fold.last_at))
                fold.repeats = 0
        return written

    def __len__(self) -> int:
        return len(self._folds)


def _record(row: Row) -> Record:
    (principal, address, action, outcome, detail), count, at = row
    return records.audit(at, principal, address, action, outcome, detail, count)


class AuditRepeats:
    """Writes refusals to the journal through a `RepeatFolder`, and closes its windows."""

    def __init__(self, window: float, journal_of: Callable[[], Journal | None]) -> None:
        self.folder = RepeatFolder(window)
        self._journal_of = journal_of
        self._timer: asyncio.TimerHandle | None = None

    def refused(self, kind: Kind) -> None:
        """A refusal's row: written now, or folded into the row its window will write."""
        self._write(self.folder.offer(kind, time.time()))
        if len(self.folder) and self._timer is None:
            self._timer = asyncio.get_running_loop().call_later(self.folder.window, self._sweep)

    def flush(self) -> None:
        """Write every count folded so far (before the trail is read, and at shutdown)."""
        self._write(self.folder.drain())

    def close(self) -> None:
        """Write what is folded and stop closing windows (the journal is about to close)."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self.flush()

    def _sweep(self) -> None:
        self._timer = None
        self._write(self.folder.due(time.time()))
        if len(self.folder):
            self._timer = asyncio.get_running_loop().call_later(self.folder.window, self._sweep)

    def _write(self, rows: list[Row]) -> None:
        journal = self._journal_of()
        if rows and journal is not None:
            journal.append([_record(row) for row in rows], durable=False)
