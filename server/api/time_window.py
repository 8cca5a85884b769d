"""The `since` / `until` window every journal route takes, checked once: since before until.

Why a 422 and not an empty answer: `since=200&until=100` is a script that swapped
its bounds, and an empty table or a KPI report of nothing looks like a quiet
shift. Both bounds are Unix seconds, finite and within 0..1e11 (the year 5138).

openapi.json states the rule in words (each parameter's description) and for
tools as `x-before: until` in the `since` parameter's schema.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from fastapi import Query
from fastapi.exceptions import RequestValidationError

LATEST = 1e11  # Unix seconds; far beyond any journal, well inside a float's exact integers

Since = Annotated[
    float | None,
    Query(
        ge=0,
        le=LATEST,
        allow_inf_nan=False,
        description="Unix time, inclusive; must be before `until` when both are given",
        json_schema_extra={"x-before": "until"},
    ),
]
Until = Annotated[
    float | None,
    Query(
        ge=0,
        le=LATEST,
        allow_inf_nan=False,
        description="Unix time, exclusive; must be after `since` when both are given",
    ),
]


@dataclass(frozen=True, slots=True)
class TimeWindow:
    """`[since, until)`, either end open when not given."""

    since: float | None = None
    until: float | None = None


def time_window(since: float | None, until: float | None) -> TimeWindow:
    """The query's window; a 422 naming `since` when it is not before `until`.

    A call in each route rather than a FastAPI dependency: a dependency's parameters
    are listed after the route's own in openapi.json, and `since`, `until` read best
    first.
    """
    if since is not None and until is not None and since >= until:
        raise RequestValidationError(
            [
                {
                    "type": "value_error",
                    "loc": ("query", "since"),
                    "msg": f"must be before until (since={since!r} is not before until={until!r})",
                    "input": since,
                }
            ]
        )
    return TimeWindow(since, until)
