"""A part's verdict: the one set of words every path uses for the part a run made.

Why one function: the order card, the Last part card (through GET /operations'
`part`), the KPIs (and so OPC UA's Admin counts and the MQTT `kpis` message),
the CSV export, the MQTT run message, the webhooks' run notice and the
Prometheus counters all say what became of a part, and must say it alike. A
part is one trajectory run; `part_verdict(outcome, result, error)` judges it
from how the run ended and the inspection summary in its result:

- completed and inspected: the inspection's verdict, ``good`` or ``defective``,
  with its reasons;
- not completed (stopped, cancelled, failed, cut short by a restart):
  ``defective``, not inspected, the first reason saying why (the part did not
  get its whole bead);
- completed but not inspected: ``not_inspected``, the reason saying why
  ("inspection_enabled is off", or "no space" when a full disk took its image);
  but a part whose inspection had found it defective before its image could
  not be kept stays ``defective``: a missing image never lets a defect pass.

The inspection summary is the inspection's contract (server/quality/):
``result["inspection"] = {"verdict": "good" | "defective", "reasons": [...],
"precision_mean_mm", "precision_p95_mm", "dispensing_cv_percent", "glue_ml",
"vision_residual_mm", "image"}``. A summary whose verdict is neither good nor
defective is treated as no inspection rather than guessed at.

Pure: no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final

GOOD: Final = "good"
DEFECTIVE: Final = "defective"
NOT_INSPECTED: Final = "not_inspected"
# Every verdict a part can have, in the order the counts list them.
PART_VERDICTS: Final = (GOOD, DEFECTIVE, NOT_INSPECTED)
# What an inspection itself can find.
VERDICTS: Final = (GOOD, DEFECTIVE)
# The summary's figures, each a float or None (not measured).
FIGURES: Final = (
    "precision_mean_mm",
    "precision_p95_mm",
    "dispensing_cv_percent",
    "glue_ml",
    "vision_residual_mm",
)
# The run's error when a STOP (the emergency stop) ended it: the event's name.
EMERGENCY_STOP: Final = "EMERGENCY_STOP"
# Why a completed part was not inspected when its result does not say.
INSPECTION_OFF: Final = "inspection_enabled is off"


@dataclass(frozen=True, slots=True)
class PartVerdict:
    """What became of one part: its verdict, whether an inspection judged it, and why.

    `reasons` are sentences: why it is defective, or why it was not inspected
    (then first). `label` is the words a person reads: "good", "defective",
    "defective (not inspected)" or "not inspected (why)".
    """

    verdict: str
    inspected: bool
    reasons: tuple[str, ...] = ()

    @property
    def label(self) -> str:
        if self.verdict == NOT_INSPECTED:
            return self.reasons[0] if self.reasons else "not inspected"
        if self.verdict == DEFECTIVE and not self.inspected:
            return "defective (not inspected)"
        return self.verdict

    def as_dict(self) -> dict[str, Any]:
        """The verdict as every message carries it: verdict, inspected, reasons, label."""
        return {
            "verdict": self.verdict,
            "inspected": self.inspected,
            "reasons": list(self.reasons),
            "label": self.label,
        }


def inspection_of(result: Any) -> Mapping[str, Any] | None:
    """The inspection summary of a run's result, or None when its part was not inspected."""
    if not isinstance(result, Mapping):
        return None
    inspection = result.get("inspection")
    if not isinstance(inspection, Mapping) or inspection.get("verdict") not in VERDICTS:
        return None
    return inspection


def _sentences(value: Any) -> tuple[str, ...]:
    return tuple(str(r) for r in value) if isinstance(value, list | tuple) else ()


def why_not_completed(outcome: str, error: str | None) -> str:
    """Why a run that did not complete left a defective part, in words."""
    if outcome == "cancelled":
        return "run cancelled"
    if outcome == "interrupted":
        return "run cut short: the server stopped during it"
    if error == EMERGENCY_STOP:
        return "run stopped: emergency stop (STOP)"
    return f"run failed: {error or outcome}"


def part_verdict(outcome: str, result: Any, error: str | None = None) -> PartVerdict:
    """The verdict of the part a trajectory run made, from how it ended (`outcome`:
    completed, failed, cancelled, interrupted), its `result` and its `error`."""
    if outcome != "completed":
        return PartVerdict(DEFECTIVE, False, (why_not_completed(outcome, error),))
    inspection = inspection_of(result)
    if inspection is not None:
        return PartVerdict(str(inspection["verdict"]), True, _sentences(inspection.get("reasons")))
    why = result.get("not_inspected") if isinstance(result, Mapping) else None
    reason = f"not inspected ({why if isinstance(why, str) and why else INSPECTION_OFF})"
    found = result.get("inspection_found") if isinstance(result, Mapping) else None
    if isinstance(found, Mapping) and found.get("verdict") == DEFECTIVE:
        # What the inspection found stands, image or not: no defect passes as good.
        return PartVerdict(DEFECTIVE, False, (reason, *_sentences(found.get("reasons"))))
    return PartVerdict(NOT_INSPECTED, False, (reason,))


def figure_of(inspection: Mapping[str, Any], name: str) -> float | None:
    """One of the summary's figures, or None when it was not measured (or is not a number)."""
    value = inspection.get(name)
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if math.isfinite(value) else None


def verdict_details(operation: str, outcome: str, result: Any, error: str | None) -> dict[str, Any]:
    """What a run message (MQTT, webhook) says of the part: `part_verdict`'s fields and the
    inspection summary.

    A run that makes no part (a calibration, a create-workpiece) has `verdict` null,
    `inspected` false, `reasons` [] and `label` null; `inspection` is the summary as the
    run record holds it (null when none), so a receiver has the figures without asking
    GET /runs/{run_id}/inspection.
    """
    inspection = inspection_of(result)
    summary = dict(inspection) if inspection is not None else None
    if operation != "trajectory":
        return {
            "verdict": None,
            "inspected": False,
            "reasons": [],
            "label": None,
            "inspection": summary,
        }
    return {**part_verdict(outcome, result, error).as_dict(), "inspection": summary}
