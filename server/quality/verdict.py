"""The part's verdict from the run's figures: good, or defective with the reasons.

Pure: each reason is a sentence a technician can act on, naming the segment
or the device and the figure against its tolerance (the setting's value).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the image process imports this module (look.py): no settings there
    from server.settings.quality import QualitySettings


def precision_reasons(precision: dict[str, Any], settings: QualitySettings) -> list[str]:
    limit = settings.trajectory_precision_limit_mm
    return [
        f"segment {s['index']}: the robot strayed up to {s['max_mm']:.2f} mm from the planned "
        f"path (at most {limit:g} mm, trajectory_precision_limit_mm)"
        for s in precision["segments"]
        if s["max_mm"] is not None and s["max_mm"] > limit
    ]


def dispensing_reasons(dispensing: dict[str, Any], settings: QualitySettings) -> list[str]:
    reasons = []
    tolerance = settings.dispensing_flow_tolerance_percent
    longest = settings.dispensing_max_out_of_tolerance_s
    if dispensing["out_of_tolerance_s"] > longest:
        reasons.append(
            f"glue flow out of tolerance for {dispensing['out_of_tolerance_s']:.2f} s while "
            f"spraying (at most {longest:g} s): mean {dispensing['flow_mean_ml_min']:.1f} ml/min "
            f"against its setpoint {dispensing['setpoint_ml_min']:.1f} ml/min ± {tolerance:g} %; "
            "check the nozzle and the glue supply"
        )
    ratio = dispensing["glue_ratio_percent"]
    volume = settings.glue_volume_tolerance_percent
    if ratio is not None and abs(ratio - 100.0) > volume:
        reasons.append(
            f"glue dispensed {dispensing['glue_ml']:.3f} ml, {ratio:.0f} % of the "
            f"{dispensing['expected_ml']:.3f} ml the path needs (within ± {volume:g} %, "
            "glue_volume_tolerance_percent); check the nozzle, the glue supply and the valve"
        )
    return reasons


def part_reasons(parts: Sequence[dict[str, Any]], limit: float) -> list[str]:
    """Why each part's bead cannot be trusted: not found again, or moved over `limit`
    (bead_max_offset_mm) since it was matched."""
    reasons = []
    for part in parts:
        name = part["workpiece_id"]
        if not part["found"]:
            reasons.append(
                f"workpiece {name}: not found again on the inspection frame; its bead is "
                "judged where it was matched"
            )
        elif part["moved_mm"] > limit:
            reasons.append(
                f"workpiece {name}: moved {part['moved_mm']:.1f} mm since it was matched "
                f"(at most {limit:g} mm, bead_max_offset_mm): the bead is off the part"
            )
    return reasons


def verdict_of(reasons: Sequence[str]) -> str:
    return "defective" if reasons else "good"
