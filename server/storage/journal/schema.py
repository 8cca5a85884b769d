"""What the journal derives from its tables' declarations (`tables.py`), for the writer,
the readers, the commit chain and the HTTP routes:

- `SCHEMA`, the SQL that creates the tables and their time indexes at open;
- `TABLES`, the record tables by name: readers, exports, retention and the
  commit chain read a table's `column_names` and `time_column` from it;
- `FILTERS`, each table's equality filters: the readers refuse any other
  column, and the HTTP routes (server/api/analytics.py) build their query
  parameters, with type and description, from it;
- `SEALED`, `COMMIT_SEQ`, `LATER_COLUMNS` and `sealed_form`, for the commit chain;
- `PART_FIGURES`, the inspection figures a part of an order carries.

The record builders (`records.py`) name columns the declarations check.
"""

from __future__ import annotations

from typing import Any

from server.storage.journal.declaration import Filter, Table
from server.storage.journal.tables import ALL_TABLES, ORDER_PARTS

# The column a sealed row carries: the sequence number of the commit that appended it.
COMMIT_SEQ = "commit_seq"

SCHEMA = "\n".join(table.create_sql() for table in ALL_TABLES) + "\n"

# The record tables (queried, exported, pruned by their time column), by name.
TABLES: dict[str, Table] = {t.name: t for t in ALL_TABLES if not t.internal}

# The journal's own tables (the commit chain, its start, the write check), by name.
INTERNAL: dict[str, Table] = {t.name: t for t in ALL_TABLES if t.internal}

# The tables whose rows are sealed: each row carries the sequence number of the
# commit that appended it (`commit_seq`, added to older journals at open) and is part
# of that commit's digest. A table added later is created at open with its commit_seq
# added like the others', and counts from 0 in the first commit that appends to it.
SEALED: tuple[str, ...] = tuple(name for name, t in TABLES.items() if t.sealed)

# Per table, its columns added after journals were written without them: (name, SQL
# declaration, the value every older row takes).
LATER_COLUMNS: dict[str, tuple[tuple[str, str, object], ...]] = {
    name: tuple((c.name, c.sql, c.older_rows) for c in t.later_columns)
    for name, t in TABLES.items()
    if t.later_columns
}

FILTERS: dict[str, tuple[Filter, ...]] = {name: t.filters for name, t in TABLES.items()}

# The inspection figures a part of an order carries (server/orders/model.py).
PART_FIGURES: tuple[str, ...] = tuple(c.name for c in ORDER_PARTS.columns if c.part_figure)


def sealed_form(table: str, row: tuple[Any, ...]) -> tuple[Any, ...]:
    """A row (TABLES' columns) as the commit chain digests it: a LATER_COLUMNS column that
    ends the row and holds its default is left out, as the row was before the column was."""
    later = LATER_COLUMNS.get(table)
    if later is None:
        return row
    for _, _, default in reversed(later):
        if row and row[-1] == default:
            row = row[:-1]
        else:
            break
    return row


def filter_columns(table: str) -> tuple[str, ...]:
    """The names of the columns `table` may be filtered on."""
    return tuple(f.column for f in FILTERS[table])


def time_column(table: str) -> str:
    """The column that orders, ranges and prunes the rows of the record table `table`."""
    column = TABLES[table].time_column
    assert column is not None, f"{table} has no time column"
    return column


def column_names(table: str) -> tuple[str, ...]:
    """The columns of the record table `table`, in the order rows are read and sealed."""
    return TABLES[table].column_names
