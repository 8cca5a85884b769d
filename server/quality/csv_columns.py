"""The inspection's figures as columns of the operations CSV export.

Taken from the summary in each run's result (the run record's `result`), so
the export needs no join: a run without an inspection has the columns empty.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

from server.quality.part_verdict import FIGURES

# The summary's verdict and reasons, then each of its figures (declared in part_verdict).
INSPECTION_COLUMNS: tuple[str, ...] = ("verdict", "reasons", *FIGURES)


def inspection_values(result: Any) -> list[Any]:
    """The INSPECTION_COLUMNS of one operations row's `result` (JSON text or None)."""
    try:
        data = json.loads(result) if isinstance(result, str) else None
    except ValueError:
        data = None
    summary = data.get("inspection") if isinstance(data, dict) else None
    if not isinstance(summary, dict):
        return [""] * len(INSPECTION_COLUMNS)
    values: list[Any] = []
    for column in INSPECTION_COLUMNS:
        value = summary.get(column)
        if column == "reasons":
            value = " | ".join(value or [])
        values.append("" if value is None else value)
    return values


def with_inspection(columns: Sequence[str], rows: Sequence[Sequence[Any]]) -> list[list[Any]]:
    """Operations rows (in `columns` order) with the inspection's columns appended."""
    at = list(columns).index("result")
    return [[*row, *inspection_values(row[at])] for row in rows]
