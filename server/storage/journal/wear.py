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

from server.storage.journal import records as rows
from server.storage.journal.records import Record


def records(values: Mapping[str, float], at: float) -> list[Record]:
    """One row per key, replacing the one before."""
    return [rows.wear(key, value, at) for key, value in values.items()]


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


def written_at(path: Path) -> float | None:
    """When the totals were last written (Unix seconds); None for a journal without any."""
    if not path.exists():
        return None
    connection = sqlite3.connect(path, timeout=30)
    try:
        (latest,) = connection.execute("SELECT MAX(time) FROM wear").fetchone()
    except sqlite3.OperationalError:  # a journal opened before the table was declared
        return None
    finally:
        connection.close()
    return float(latest) if latest is not None else None
