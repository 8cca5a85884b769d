"""Check a journal file by hand: every commit, or the newest N, read-only.

`python -m server.storage.journal.check data/journal.db` prints "ok: ..." or
each thing found wrong (exit 1), as start-up would say it but over every commit
rather than the newest 10 000 (see `verify.py`). It only reads, in one
snapshot, so it may run while the server writes.
"""

from __future__ import annotations

import argparse
import sqlite3
import sys
from pathlib import Path

from server.storage.journal.commit_chain import LastCommitFile
from server.storage.journal.verify import verify


def check(journal: Path, window: int | None = None) -> list[str]:
    """What is wrong with the journal file, one line each (empty: nothing), or the line
    "ok: ..." first when nothing is. Read-only, in one snapshot."""
    found: list[str] = []
    try:
        noted = LastCommitFile(journal).read()
    except (OSError, ValueError) as exc:
        noted = None
        found.append(f"the last-commit record is unreadable ({exc})")
    connection = sqlite3.connect(f"{journal.resolve().as_uri()}?mode=ro", uri=True)
    try:
        # One snapshot for every query, taken after the note was read: a server
        # committing meanwhile is neither half seen nor taken for damage.
        connection.execute("BEGIN")
        quick = connection.execute("PRAGMA quick_check").fetchone()
        if quick is None or quick[0] != "ok":
            raise sqlite3.DatabaseError(f"quick_check: {quick}")
        verdict = verify(connection, noted, window=window)
    except sqlite3.DatabaseError as exc:
        return [*found, f"SQLite cannot read {journal}: {exc}"]
    finally:
        connection.close()
    found += [damage.message for damage in verdict.damage]
    if not found:
        return [f"ok: commits up to {verdict.head.seq}, {verdict.digested} digested again"]
    return found


def main(argv: list[str] | None = None) -> int:
    """Check a journal file, every commit by default; print what is wrong (exit 1) or ok."""
    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("journal", type=Path, help="the journal, e.g. data/journal.db")
    parser.add_argument("--window", type=int, default=None, help="digest only the newest N commits")
    args = parser.parse_args(argv)
    if not args.journal.is_file():
        print(f"no journal at {args.journal}", file=sys.stderr)
        return 2
    lines = check(args.journal, args.window)
    for line in lines:
        print(line)
    return 0 if lines[0].startswith("ok: ") else 1


if __name__ == "__main__":
    sys.exit(main())
