"""The journal's `wear` table: counters and maintenance marks, one row per key.

Rows are replaced, never appended: the table holds the totals as of the last write
(`record`), and start-up reads them back (`read`), so the counts go on across
restarts. Internal to the journal (not sealed, never pruned by retention): wear is
the cell's life, not a record of one day.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Mapping
from pathlib import Path

from server.storage.journal.records import Record, _row


def records(values: Mapping[str, float], at: float) -> list[Record]:
    """One row per key, replacing the one before."""
    return [_row("wear", replace=True, key=k, value=float(v), time=at) for k, v in values.items()]


def read(path: Path) -> dict[str, float]:
    """Every key and its value as last written; empty for a journal without any."""
    if not path.exists():
        return {}
    connection = sqlite3.connect(path, timeout=30)
    try:
        rows = connection.execute("SELECT key, value FROM wear").fetchall()
    except sqlite3.OperationalError:  # a journal opened before the table was declared
        return {}
    finally:
        connection.close()
    return {str(key): float(value) for key, value in rows}
