"""`gluectl line`'s table: one row per cell of the line, as the broker has them."""

from __future__ import annotations

from typing import Any

from rich.table import Table
from rich.text import Text

from clients.line_model import CellRow, LineModel

DASH = "—"


def _link(row: CellRow) -> Text:
    if row.online is None:
        return Text("?", style="dim")
    return Text("online", style="green") if row.online else Text("offline", style="bold red")


def _stop_reason(reason: dict[str, Any] | None) -> str:
    if not reason:
        return DASH
    code, message = reason.get("code"), reason.get("message")
    return f"{code}: {message}" if code and message else str(code or message or DASH)


def _progress(progress: dict[str, Any] | None) -> str:
    if not progress:
        return DASH
    fraction = progress.get("fraction")
    shown = f"{100 * fraction:.0f} %" if isinstance(fraction, int | float) else DASH
    return f"{shown} ({progress.get('waypoint', '?')}/{progress.get('total', '?')})"


def _oee(oee: float | None) -> str:
    return DASH if oee is None else f"{oee * 100:.1f} %"


def line_table(model: LineModel, broker: str) -> Table:
    """The cells under the model's prefix; a cell whose last will fired reads `offline`."""
    table = Table(title=f"line: {broker}, prefix {model.prefix}", title_justify="left")
    for column in ("cell", "link", "state", "stop reason", "run", "progress", "OEE"):
        table.add_column(column, overflow="fold")
    for row in model.rows():
        table.add_row(
            row.cell_id,
            _link(row),
            row.state or DASH,
            _stop_reason(row.stop_reason),
            row.run_id or DASH,
            _progress(row.shown_progress()),
            _oee(row.oee),
        )
    if not model.cells:
        table.caption = "no cell has published under this prefix yet"
    return table
