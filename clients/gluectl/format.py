"""gluectl's text forms: a time, a value, a fault, a run's progress, a key/value table
(shared by its modules)."""

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


def fault_line(fault: dict[str, Any] | None) -> str:
    """A fault (or stop reason) on one line: code, message, what to do."""
    if not fault:
        return "—"
    return f"{fault.get('code')}: {fault.get('message')} ({fault.get('recommended_action', '')})"


def progress_line(progress: dict[str, Any] | None) -> str:
    """A run's progress on one line, empty before the first waypoint's total is known."""
    if not progress or not progress.get("total"):
        return ""
    fraction = progress.get("fraction") or 0.0
    return f"waypoint {progress.get('waypoint')}/{progress['total']} ({fraction:.0%})"
