"""The audit table's `count` column on real SQLite: a journal written before it existed
opens, gets the column (every older row counts 1), and its commit chain still verifies."""

from __future__ import annotations

import asyncio
import sqlite3
import time

from server.storage.journal import Journal, records


async def test_a_journal_without_the_count_column_verifies_and_takes_folded_rows(tmp_path):
    journal = Journal(tmp_path / "journal.db")
    journal.open()
    journal.start(asyncio.get_running_loop())
    written = journal.append(
        [records.audit(time.time(), "anonymous", "10.0.0.5", "GET /state", "refused (401)", "x")]
    )
    assert written is not None
    await written
    journal.stop()
    with sqlite3.connect(journal.path) as connection:  # as an older version left it
        connection.execute("ALTER TABLE audit DROP COLUMN count")

    reopened = Journal(journal.path)
    reopened.open()
    assert reopened.damage == []
    reopened.start(asyncio.get_running_loop())
    folded = reopened.append(
        [
            records.audit(
                time.time(), "anonymous", "10.0.0.5", "GET /state", "refused (401)", "x", 41
            )
        ]
    )
    assert folded is not None
    await folded
    rows = await asyncio.to_thread(reopened.query, "audit")
    assert sorted(row["count"] for row in rows) == [1, 41]
    reopened.stop()

    again = Journal(journal.path)
    again.open()
    assert again.damage == []  # the folded row is sealed with its count
    with sqlite3.connect(journal.path) as connection:  # and a count changed is noticed
        connection.execute("UPDATE audit SET count = 40 WHERE count = 41")
    changed = Journal(journal.path)
    changed.open()
    assert changed.damage and "audit" in changed.damage[0].message
