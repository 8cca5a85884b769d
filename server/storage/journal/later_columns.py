"""Older journals brought up to the declared schema: the columns added since they were written.

Kept apart from `tables.py`, which declares the tables: these read a journal file's own
columns (PRAGMA table_info) and add or stand in for what it lacks.
"""

from __future__ import annotations

import sqlite3

from server.storage.journal.schema import COMMIT_SEQ, LATER_COLUMNS, SEALED, TABLES


def add_commit_seq(connection: sqlite3.Connection) -> None:
    """Give each sealed table its `commit_seq` column where an older journal lacks it,
    and each table the LATER_COLUMNS it lacks."""
    for table in SEALED:
        columns = {row[1] for row in connection.execute(f"PRAGMA table_info({table})")}
        if COMMIT_SEQ not in columns:
            connection.execute(f"ALTER TABLE {table} ADD COLUMN {COMMIT_SEQ} INTEGER")
    for table, later in LATER_COLUMNS.items():
        columns = {row[1] for row in connection.execute(f"PRAGMA table_info({table})")}
        for name, declaration, _ in later:
            if name not in columns:
                connection.execute(f"ALTER TABLE {table} ADD COLUMN {name} {declaration}")


def stored_columns(connection: sqlite3.Connection, table: str) -> str:
    """TABLES' columns of `table` for a SELECT, a LATER_COLUMNS one the file does not have
    yet as its default (the journal is verified before it is opened and given it)."""
    have = {row[1] for row in connection.execute(f"PRAGMA table_info({table})")}
    defaults = {name: default for name, _, default in LATER_COLUMNS.get(table, ())}
    return ", ".join(
        name if name in have or name not in defaults else f"{defaults[name]!r} AS {name}"
        for name in TABLES[table].column_names
    )
