"""What checking the journal costs at start-up, on a journal of a million rows.

The journal is built through the real commit chain (`commit_chain.py`), three
rows per commit as a command writes them (its event, its transition, its audit
row), runs started and completed in turn so it ends in IDLE (bench/startup.py
starts a server on it), then checked the way `Journal.open` does: PRAGMA quick_check (SQLite's
own check, there before the chain), then `verify` over the newest WINDOW
commits (what start-up digests again), and, for comparison, over every commit
(what `python -m server.storage.journal.check <journal.db>` does on demand).
"""

from __future__ import annotations

import argparse
import logging
import sqlite3
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.report import emit
from server.storage.journal import SCHEMA, records
from server.storage.journal.commit_chain import GENESIS, CommitChain, LastCommitFile
from server.storage.journal.later_columns import add_commit_seq
from server.storage.journal.verify import WINDOW, verify

PER_TRANSACTION = 1_000  # commits written per SQLite transaction while building
RUN_STARTED = ("START_REQUESTED", "IDLE", "EXECUTING_TRAJECTORY")  # event, from, to
RUN_COMPLETED = ("OPERATION_COMPLETED", "EXECUTING_TRAJECTORY", "IDLE")


def build(path: Path, rows: int) -> int:
    """A journal of about `rows` sealed rows; returns how many commits it holds."""
    connection = sqlite3.connect(path)
    connection.execute("PRAGMA journal_mode=WAL")
    connection.execute("PRAGMA synchronous=OFF")
    connection.executescript(SCHEMA)
    add_commit_seq(connection)
    chain = CommitChain(GENESIS, LastCommitFile(path))
    commits = rows // 3 // 2 * 2  # even: the last commit is a run completed, back in IDLE
    at = time.time() - 60  # the past, within any retention
    for start in range(0, commits, PER_TRANSACTION):
        with connection:
            for i in range(start, min(commits, start + PER_TRANSACTION)):
                event_id = f"event-{i:08d}"
                event, old, new = RUN_STARTED if i % 2 == 0 else RUN_COMPLETED
                head = chain.write(
                    connection,
                    [
                        records.event(event_id, at, event, "api", {}, "accepted", "", old),
                        records.transition(
                            {
                                "timestamp": at,
                                "old_state": old,
                                "new_state": new,
                                "event": event,
                                "event_id": event_id,
                                "time_in_old_state": 12.5,
                            }
                        ),
                        records.audit(
                            at, "operator:line-1", "10.0.0.7", "POST /start", "accepted", event_id
                        ),
                    ],
                    at,
                )
                assert head is not None
                chain.committed(head)
    chain.close()
    connection.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    connection.close()
    return commits


def timed(path: Path, what: str, window: int | None = None) -> tuple[float, int]:
    connection = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True)
    try:
        started = time.perf_counter()
        if what == "quick_check":
            assert connection.execute("PRAGMA quick_check").fetchone()[0] == "ok"
            digested = 0
        else:
            verdict = verify(connection, LastCommitFile(path).read(), window=window)
            assert not verdict.damage, verdict.damage
            digested = verdict.digested
        return time.perf_counter() - started, digested
    finally:
        connection.close()


def run(rows: int) -> list[dict[str, Any]]:
    results = []
    with tempfile.TemporaryDirectory() as name:
        path = Path(name) / "journal.db"
        started = time.perf_counter()
        commits = build(path, rows)
        built_s = time.perf_counter() - started
        size_mb = round(path.stat().st_size / 1e6, 1)
        for check, window in (("quick_check", None), ("verify", WINDOW), ("verify", None)):
            elapsed, digested = timed(path, check, window)
            results.append(
                {
                    "check": check
                    if check == "quick_check"
                    else f"verify window={window or 'all'}",
                    "rows": commits * 3,
                    "commits": commits,
                    "commits_digested": digested,
                    "seconds": round(elapsed, 3),
                    "file_mb": size_mb,
                    "build_s": round(built_s, 1),
                }
            )
    return results


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--rows", type=int, default=1_000_000)
    args = parser.parse_args(argv)
    logging.disable(logging.ERROR)
    rows = run(args.rows)
    emit("journal_verify", rows, {"rows": args.rows, "window": WINDOW})
    return rows


if __name__ == "__main__":
    main()
