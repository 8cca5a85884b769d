"""The settings PATCH /settings may change, and the body that changes them.

Why the body is a model built from `Settings` itself: each setting's type,
bounds and description are declared once, in its section (server/settings/), and the request
must enforce exactly those, strictly (a number never as "8" or true, never
Infinity or 1e400), and state them in openapi.json. A hand-written copy would
drift from them: a body of any JSON object promises nothing in openapi.json and
takes `{"design_cycle_time_s": Infinity}`.

A setting not listed here is refused as an unknown field: it needs a restart.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, StrictBool, create_model

from server.common.values import FiniteNumber, whole_number
from server.settings.model import Settings

RUNTIME_SETTINGS = (
    "error_state_timeout",
    "auto_recovery_enabled",
    "error_recovery_attempts",
    "error_recovery_delay",
    "calibration_max_error_mm",
    "design_cycle_time_s",
    "shift_hours",
    "processing_timeout",
    "logging_level",
    # The quality engineer's: whether parts are judged, and against what (docs/quality.md)
    "inspection_enabled",
    "trajectory_precision_limit_mm",
    "dispensing_flow_tolerance_percent",
    "dispensing_max_out_of_tolerance_s",
    "glue_volume_tolerance_percent",
    "bead_width_tolerance_percent",
    "bead_max_gap_mm",
    "bead_max_offset_mm",
    "order_defect_limit",
    # The maintenance technician's: the schedule and the glue line (operations guide)
    "maintenance_items",
    "maintenance_overdue_percent",
    "purge_seconds",
    "purge_flow_ml_min",
    "pot_life_minutes",
    "pot_life_warning_percent",
    "glue_reservoir_ml",
    "glue_low_level_percent",
)


def _strict(kind: Any, constraints: list[Any]) -> Any:
    """The strict form of a setting's type (server/common/values.py), with its bounds."""
    if kind is float:
        return Annotated[FiniteNumber, *constraints]
    if kind is int:
        return whole_number(*constraints)
    if kind is bool:
        return StrictBool
    return Annotated[kind, *constraints] if constraints else kind  # a Literal: exact already


def _without_defaults(schema: dict[str, Any]) -> None:
    """A PATCH has no defaults: a setting left out keeps its value (GET /settings shows it)."""
    for field in schema.get("properties", {}).values():
        field.pop("default", None)


def _change_model() -> type[BaseModel]:
    fields: dict[str, Any] = {}
    for name in RUNTIME_SETTINGS:
        declared = Settings.model_fields[name]
        annotation = _strict(declared.annotation, declared.metadata)
        fields[name] = (annotation, Field(None, description=declared.description))
    return create_model(
        "SettingsChange",
        __config__=ConfigDict(extra="forbid", json_schema_extra=_without_defaults),
        __doc__="The settings to change at once; each keeps its bounds and type from the "
        "settings model. Any other key is refused: it takes effect only at a restart.",
        **fields,
    )


if TYPE_CHECKING:
    SettingsChange = BaseModel
else:
    SettingsChange = _change_model()


def plan_change(settings: Settings, change: BaseModel) -> dict[str, tuple[Any, Any]]:
    """(old, new) of each field `change` was given that differs from `settings`.

    The merged whole is validated, so a rule across settings holds too
    (ValidationError); nothing is applied here: the caller puts the change on
    record first, then sets each new value.
    """
    given = change.model_dump(include=change.model_fields_set)
    merged = Settings.model_validate({**settings.model_dump(), **given})
    return {
        name: (getattr(settings, name), getattr(merged, name))
        for name in given
        if getattr(settings, name) != getattr(merged, name)
    }
