"""A run's part verdict, read from the inspection summary in its result.

Why one reader: the KPIs, the Prometheus counters, the OPC UA counts, the MQTT
run message and the webhooks' run notice all ask the same question of a run's
result (was its part inspected, and was it good?), and must answer it the same
way. The summary is the inspection's contract (server/quality/):
``result["inspection"] = {"verdict": "good" | "defective", "reasons": [...],
"precision_mean_mm", "precision_p95_mm", "dispensing_cv_percent", "glue_ml",
"vision_residual_mm", "image"}``; no "inspection" key means the part was not
inspected (inspection off, or the run did not complete). A summary whose
verdict is neither good nor defective is treated as not inspected rather than
guessed at, so a malformed record never counts as a part.

Pure: no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Final

VERDICTS: Final = ("good", "defective")
# The summary's figures, each a float or None (not measured).
FIGURES: Final = (
    "precision_mean_mm",
    "precision_p95_mm",
    "dispensing_cv_percent",
    "glue_ml",
    "vision_residual_mm",
)


def inspection_of(result: Any) -> Mapping[str, Any] | None:
    """The inspection summary of a run's result, or None when its part was not inspected."""
    if not isinstance(result, Mapping):
        return None
    inspection = result.get("inspection")
    if not isinstance(inspection, Mapping) or inspection.get("verdict") not in VERDICTS:
        return None
    return inspection


def verdict_of(result: Any) -> str | None:
    """ "good", "defective", or None (not inspected)."""
    inspection = inspection_of(result)
    return None if inspection is None else str(inspection["verdict"])


def reasons_of(result: Any) -> list[str]:
    """Why the part is defective, as sentences; empty for a good or uninspected part."""
    inspection = inspection_of(result)
    reasons = inspection.get("reasons") if inspection is not None else None
    return [str(reason) for reason in reasons] if isinstance(reasons, list) else []


def figure_of(inspection: Mapping[str, Any], name: str) -> float | None:
    """One of the summary's figures, or None when it was not measured (or is not a number)."""
    value = inspection.get(name)
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if math.isfinite(value) else None


def verdict_details(result: Any) -> dict[str, Any]:
    """What a run message (MQTT, webhook) says of the part: verdict, reasons, the summary.

    `verdict` is null for a part that was not inspected; `inspection` is the
    summary as the run record holds it (null likewise), so a receiver has the
    figures without asking GET /runs/{run_id}/inspection.
    """
    inspection = inspection_of(result)
    return {
        "verdict": verdict_of(result),
        "reasons": reasons_of(result),
        "inspection": dict(inspection) if inspection is not None else None,
    }
