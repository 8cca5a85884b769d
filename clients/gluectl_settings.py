"""What `gluectl settings get|set` shows and sends: the table of settings with where each
value comes from, and NAME=VALUE words turned into a PATCH /settings body.

Kept apart from gluectl.py, which holds the commands themselves, so each stays short.
"""

from __future__ import annotations

import json
from typing import Any

from rich.table import Table
from rich.text import Text

META_KEYS = ("sources", "runtime_settings")


def settings_rows(data: dict[str, Any], names: list[str] | None = None) -> list[dict[str, Any]]:
    """One row per setting of GET /settings (or only `names`): name, value, source, and
    whether a change applies at once (`runtime`) or needs a restart.

    Raises KeyError naming a setting in `names` the server does not have."""
    sources = data.get("sources") or {}
    runtime = set(data.get("runtime_settings") or ())
    wanted = names or [key for key in data if key not in META_KEYS]
    rows = []
    for name in wanted:
        if name not in data or name in META_KEYS:
            raise KeyError(name)
        rows.append(
            {
                "name": name,
                "value": data[name],
                "source": sources.get(name, "unknown"),
                "changes": "at once" if name in runtime else "at a restart",
            }
        )
    return rows


def settings_table(rows: list[dict[str, Any]]) -> Table:
    table = Table(title="settings", title_justify="left")
    for column in ("setting", "value", "from", "a change applies"):
        table.add_column(column, overflow="fold")
    for row in rows:
        value = json.dumps(row["value"], ensure_ascii=False)
        table.add_row(*(Text(v) for v in (row["name"], value, row["source"], row["changes"])))
    return table


def parse_assignments(words: list[str]) -> dict[str, Any]:
    """`NAME=VALUE` words as a body: each value read as JSON (10, true, 2.5), else as text
    (INFO). ValueError for a word without `=` or with an empty name."""
    body: dict[str, Any] = {}
    for word in words:
        name, equals, text = word.partition("=")
        if not equals or not name.strip():
            raise ValueError(f"{word!r}: expected NAME=VALUE, e.g. shift_hours=10")
        try:
            body[name.strip()] = json.loads(text)
        except ValueError:
            body[name.strip()] = text
    return body
