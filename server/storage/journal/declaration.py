"""How a journal table is declared: `Column`, `Table`, and the `Filtered`/`Filter` pair
that says which columns a query may filter on by equality.

A `Table` lists its `Column`s in the order rows are read, exported and sealed; each
column carries its SQL declaration, the Python type of its value as read back, one
line saying what it holds, and whether a query may filter on it. The tables
themselves are declared in `tables.py`; what is derived from them for the whole
journal (the SQL, the filters, the sealed tables) is in `schema.py`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any, Final


class _Always:
    """The `older_rows` of a column every journal has had since its table was made."""

    def __repr__(self) -> str:
        return "ALWAYS"


ALWAYS: Final = _Always()


@dataclass(frozen=True, slots=True)
class Filtered:
    """How a query may filter a column by equality."""

    # False: only the CSV export offers it, not the table's JSON route (which never did).
    on_json_route: bool = True
    # The values the column can hold, when they are a closed set: any other is a 422
    # naming the parameter (a typo such as outcome=faild matched no row, silently).
    values: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class Column:
    """One column: name, SQL declaration, the Python type read back, what it holds.

    `py` is the value's type as the API serves it: `str`, `int`, `float`, `bool`
    (stored 0 or 1), or `dict`/`list` (stored as JSON text). A column is NULL-able
    when its SQL says neither NOT NULL nor PRIMARY KEY.
    """

    name: str
    sql: str  # what follows the name in CREATE TABLE, e.g. "TEXT NOT NULL"
    py: type
    meaning: str
    filter: Filtered | None = None
    # A column added after journals were written without it: the value every older
    # row takes. Added at open (`later_columns.add_commit_seq`), and a sealed row holding it is
    # digested without it (`sealed_form`), so older commits verify as before.
    older_rows: object = ALWAYS
    # On `order_parts`: a figure of the run's inspection summary, copied onto the part.
    part_figure: bool = False

    @property
    def sql_type(self) -> str:
        return self.sql.split()[0]

    @property
    def nullable(self) -> bool:
        return "NOT NULL" not in self.sql and "PRIMARY KEY" not in self.sql

    @property
    def generated(self) -> bool:
        """SQLite numbers it: a record never gives it."""
        return "AUTOINCREMENT" in self.sql

    @property
    def json(self) -> bool:
        return self.py in (dict, list)


@dataclass(frozen=True, slots=True)
class Filter:
    """A column a query may filter on by equality (derived from its `Column`)."""

    column: str
    type: type  # of the value compared with the column
    meaning: str  # one line: what the column holds (documents the query parameter)
    on_json_route: bool = True
    values: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class Table:
    """A journal table. `time_column` orders, ranges and prunes its rows; `sealed` rows
    carry `commit_seq` and are digested by the commit chain; an `internal` table is the
    journal's own bookkeeping, never queried, exported or pruned by its time."""

    name: str
    meaning: str
    columns: tuple[Column, ...]
    time_column: str | None = "time"
    sealed: bool = False
    internal: bool = False
    indexes: tuple[tuple[str, str], ...] = ()  # (index name, column)

    @property
    def column_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.columns)

    @property
    def filters(self) -> tuple[Filter, ...]:
        """The columns a query may filter on, in column order."""
        return tuple(
            Filter(c.name, c.py, c.meaning, c.filter.on_json_route, c.filter.values)
            for c in self.columns
            if c.filter is not None
        )

    @property
    def later_columns(self) -> tuple[Column, ...]:
        return tuple(c for c in self.columns if c.older_rows is not ALWAYS)

    def column(self, name: str) -> Column:
        for c in self.columns:
            if c.name == name:
                return c
        raise KeyError(f"{self.name} has no column {name!r}")

    def create_sql(self) -> str:
        body = ",\n    ".join(f"{c.name} {c.sql}" for c in self.columns)
        indexes = "".join(
            f"\nCREATE INDEX IF NOT EXISTS {index} ON {self.name}({column});"
            for index, column in self.indexes
        )
        create = f"CREATE TABLE IF NOT EXISTS {self.name} (\n    {body}\n);"
        return f"-- {self.meaning}\n{create}{indexes}"

    def decode(self, row: dict[str, Any]) -> dict[str, Any]:
        """A row as the API serves it: JSON columns parsed, flags as booleans."""
        for c in self.columns:
            value = row.get(c.name)
            if c.json and isinstance(value, str):
                row[c.name] = json.loads(value)
            elif c.py is bool and c.name in row:
                row[c.name] = bool(value)
        return row
