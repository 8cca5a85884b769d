"""The part's verdict and the inspection's figures as columns of the operations CSV export.

Taken from each row itself (its kind, outcome, error and `result`), so the export
needs no join. The verdict, `inspected` and the reasons are `part_verdict`'s
(server/quality/part_verdict.py), the words every other path gives the part: a
spray run that did not complete is a defective part, not inspected, with why. A
row that made no part (a calibration) has the verdict columns empty; a part
without an inspection has the figures empty.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

from server.quality.part_verdict import FIGURES, inspection_of, part_verdict

# The part's verdict and why, each inspection figure, then whether it was inspected
# (last, so the columns before it keep their places in a spreadsheet made earlier).
INSPECTION_COLUMNS: tuple[str, ...] = ("verdict", "reasons", *FIGURES, "inspected")
# The operations columns these are read from.
SOURCE_COLUMNS: tuple[str, ...] = ("kind", "outcome", "error", "result")


def inspection_values(kind: Any, outcome: Any, error: Any, result: Any) -> list[Any]:
    """The INSPECTION_COLUMNS of one operations row (`result` JSON text or None)."""
    if kind != "trajectory" or outcome is None:  # no part, or its run has not ended
        return [""] * len(INSPECTION_COLUMNS)
    try:
        data = json.loads(result) if isinstance(result, str) else None
    except ValueError:
        data = None
    judged = part_verdict(str(outcome), data, error if isinstance(error, str) else None)
    summary = inspection_of(data) or {}
    figures = ["" if (value := summary.get(name)) is None else value for name in FIGURES]
    inspected = "yes" if judged.inspected else "no"
    return [judged.verdict, " | ".join(judged.reasons), *figures, inspected]


def with_inspection(columns: Sequence[str], rows: Sequence[Sequence[Any]]) -> list[list[Any]]:
    """Operations rows (in `columns` order) with the verdict's and figures' columns appended."""
    at = [list(columns).index(name) for name in SOURCE_COLUMNS]
    return [[*row, *inspection_values(*(row[i] for i in at))] for row in rows]
