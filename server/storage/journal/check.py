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


def main(argv: list[str] | None = None) -> int:
    """Check a journal file, every commit by default; print what is wrong (exit 1) or ok."""
    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("journal", type=Path, help="the journal, e.g. data/journal.db")
    parser.add_argument("--window", type=int, default=None, help="digest only the newest N commits")
    args = parser.parse_args(argv)
    if not args.journal.is_file():
        print(f"no journal at {args.journal}", file=sys.stderr)
        return 2
    found: list[str] = []
    try:
        noted = LastCommitFile(args.journal).read()
    except (OSError, ValueError) as exc:
        noted = None
        found.append(f"the last-commit record is unreadable ({exc})")
    connection = sqlite3.connect(f"{args.journal.resolve().as_uri()}?mode=ro", uri=True)
    try:
        # One snapshot for every query, taken after the note was read: a server
        # committing meanwhile is neither half seen nor taken for damage.
        connection.execute("BEGIN")
        quick = connection.execute("PRAGMA quick_check").fetchone()
        if quick is None or quick[0] != "ok":
            raise sqlite3.DatabaseError(f"quick_check: {quick}")
        verdict = verify(connection, noted, window=args.window)
    except sqlite3.DatabaseError as exc:
        print(f"SQLite cannot read {args.journal}: {exc}")
        return 1
    finally:
        connection.close()
    found += [damage.message for damage in verdict.damage]
    for line in found:
        print(line)
    if not found:
        print(f"ok: commits up to {verdict.head.seq}, {verdict.digested} digested again")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
