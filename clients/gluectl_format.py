"""gluectl's text forms: a time, a value, a key/value table (shared by its modules)."""

from __future__ import annotations

import json
import time
from typing import Any

from rich.table import Table
from rich.text import Text


def when(timestamp: Any, *, short: bool = False) -> str:
    """Local time; `short` drops the year, for tables that must fit 80 columns."""
    if not isinstance(timestamp, int | float):
        return "—"
    return time.strftime(
        "%m-%d %H:%M:%S" if short else "%Y-%m-%d %H:%M:%S", time.localtime(timestamp)
    )


def value(value: Any) -> str:
    if value is None:
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.3f}".rstrip("0").rstrip(".") if value == value else "nan"
    if isinstance(value, dict | list):
        return json.dumps(value, ensure_ascii=False)
    return str(value)


def key_values(title: str, rows: list[tuple[str, str]]) -> Table:
    table = Table(title=title, show_header=False, title_justify="left")
    table.add_column(style="bold")
    table.add_column(overflow="fold")
    for key, value in rows:
        table.add_row(Text(key), Text(value))
    return table
