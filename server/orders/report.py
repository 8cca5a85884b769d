"""An order's report: its figures and one row per part, as JSON and as CSV.

The CSV is for a spreadsheet and a person: times in ISO 8601 (UTC), the
reasons joined with " | " in one column; the JSON keeps Unix times and lists.
"""

from __future__ import annotations

import csv
import io
from datetime import UTC, datetime
from typing import Any

from server.orders.model import Order
from server.storage.journal import PART_FIGURES

# The part's inspection figures (the journal's PART_FIGURES) sit before its reasons.
COLUMNS = (
    "part",
    "run_id",
    "started_at",
    "ended_at",
    "outcome",
    "verdict",
    "inspected",
    *PART_FIGURES,
    "reasons",
)


def report_of(order: Order) -> dict[str, Any]:
    """The order and every part made for it, in the order they were made."""
    parts = [{"part": n, **part.as_dict()} for n, part in enumerate(order.parts, start=1)]
    glue = [g for p in order.parts if (g := p.figures.get("glue_ml")) is not None]
    return {
        "order": order.as_dict(),
        "glue_ml_total": round(sum(glue), 3) if glue else None,
        "parts": parts,
    }


def _iso(at: float | None) -> str:
    return "" if at is None else datetime.fromtimestamp(at, UTC).isoformat(timespec="seconds")


def _cell(value: float | None) -> str:
    return "" if value is None else f"{value:g}"


def report_csv(order: Order) -> str:
    """The report's parts as CSV, one row per part, with a header."""
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(COLUMNS)
    for n, part in enumerate(order.parts, start=1):
        writer.writerow(
            (
                n,
                part.run_id,
                _iso(part.started_at),
                _iso(part.ended_at),
                part.outcome,
                part.verdict,
                "yes" if part.inspected else "no",
                *(_cell(value) for value in part.measured.values()),
                " | ".join(part.reasons),
            )
        )
    return buffer.getvalue()
