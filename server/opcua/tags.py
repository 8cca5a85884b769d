"""What the OPC UA tags hold, from what the bus and the KPIs say: pure functions.

Kept apart from asyncua so the shapes are tested without a server, and so the
tags say exactly what GET /state and GET /kpis say (the same snapshot, the same
KPI dict), never a second computation of them.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import Any, Final

from server.core.machine.transitions import State

# Admin's figures: the tag's name and where it is in the /kpis dict.
ADMIN_FIGURES: Final = (
    ("OEE", ("oee", "oee")),
    ("OEEAvailability", ("oee", "availability")),
    ("OEEPerformance", ("oee", "performance")),
    ("OEEQuality", ("oee", "quality")),
    ("MTBF", ("mtbf_s",)),
    ("MTTR", ("mttr_s",)),
)
# Admin's counts (names as in the OPC UA PackML companion specification) and the
# `quality` figures of /kpis they add up: every part of the shift is processed (good,
# defective, or not inspected), and a defective one is what every path calls defective
# (server/quality/part_verdict.py), a part whose run was stopped included.
ADMIN_COUNTS: Final = (
    ("ProdProcessedCount", ("parts_good", "parts_defective", "parts_not_inspected")),
    ("ProdDefectiveCount", ("parts_defective",)),
)
# What CellState keeps of each device's health: what changes when something is wrong,
# not the round-trip times that change on every request (each would be a notification).
DEVICE_FIELDS: Final = ("connected", "last_error", "active_faults")


def _dig(document: Mapping[str, Any], path: tuple[str, ...]) -> Any:
    value: Any = document
    for key in path:
        value = value.get(key) if isinstance(value, Mapping) else None
    return value


def figure(value: Any) -> float:
    """A KPI as a Double: NaN where /kpis says null (nothing to divide by yet)."""
    return float(value) if isinstance(value, int | float) else math.nan


def same(a: object, b: object) -> bool:
    """Whether a tag's value is unchanged (NaN, a KPI not known yet, equals itself here)."""
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return a == b


def admin_figures(kpis: Mapping[str, Any]) -> dict[str, float]:
    """Admin's Double tags from a /kpis dict, and TimeInState.<STATE> in seconds."""
    values = {name: figure(_dig(kpis, path)) for name, path in ADMIN_FIGURES}
    durations = kpis.get("time_in_state_s") or {}
    for state in State:
        values[f"TimeInState.{state.value}"] = figure(durations.get(state.value, 0.0))
    return values


def admin_counts(kpis: Mapping[str, Any]) -> dict[str, int]:
    """Admin's Int32 counts from a /kpis dict: the parts of the shift."""
    quality = kpis.get("quality") or {}
    return {name: sum(int(quality.get(k) or 0) for k in keys) for name, keys in ADMIN_COUNTS}


def stop_reason(snapshot: Mapping[str, Any]) -> tuple[str, str, str]:
    """The first-out stop reason's id (its code), text and component; empty when none."""
    reason = snapshot.get("stop_reason") or {}
    return (
        str(reason.get("code") or ""),
        str(reason.get("message") or ""),
        str(reason.get("component") or ""),
    )


def devices_summary(devices: Mapping[str, Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    """Each device's health, as much of it as CellState shows (DEVICE_FIELDS)."""
    return {
        name: {key: health.get(key) for key in DEVICE_FIELDS} for name, health in devices.items()
    }


def cell_state(
    snapshot: Mapping[str, Any],
    progress: Mapping[str, Any] | None,
    devices: Mapping[str, Mapping[str, Any]],
    seq: int,
) -> dict[str, Any]:
    """CellState's document: the state as /state names it, the run, workpiece, waypoint,
    devices. `seq` is the bus message it follows, so a client can tell what it missed."""
    operation = snapshot.get("operation") or {}
    progress = progress if progress is not None else (operation.get("progress") or {})
    return {
        "state": snapshot.get("state"),
        "since": snapshot.get("since"),
        "seq": seq,
        "operation": operation.get("name") or progress.get("operation"),
        "run_id": operation.get("run_id") or progress.get("run_id"),
        "workpiece_id": progress.get("workpiece_id"),
        "waypoint": progress.get("waypoint"),
        "total": progress.get("total"),
        "stop_reason": snapshot.get("stop_reason"),
        "devices": devices_summary(devices),
    }


def encode(document: Mapping[str, Any]) -> str:
    """CellState's String value: compact JSON, keys in a stable order."""
    return json.dumps(document, separators=(",", ":"), default=str)
