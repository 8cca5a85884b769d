"""The settings PATCH /settings may change, and the body that changes them.

Why the body is a model built from `Settings` itself: each setting's type,
bounds and description are declared once, in its section (server/settings/), and the request
must enforce exactly those, strictly (a number never as "8" or true, never
Infinity or 1e400), and state them in openapi.json. A hand-written copy would
drift from them: a body of any JSON object promises nothing in openapi.json and
takes `{"design_cycle_time_s": Infinity}`.

Which settings change at runtime is declared in server/settings/runtime.py
(RUNTIME_SETTINGS). Any other setting of the model is refused with the reason (it
takes effect only at a restart, and where to set it); a key that names no setting
is refused as unknown.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Any

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictBool,
    ValidationError,
    ValidatorFunctionWrapHandler,
    create_model,
    model_validator,
)
from pydantic_core import InitErrorDetails, PydanticCustomError

from server.common.values import FiniteNumber, whole_number
from server.settings.model import Settings
from server.settings.runtime import RUNTIME_SETTINGS, restart_reason

__all__ = ["RUNTIME_SETTINGS", "SettingsChange", "plan_change"]


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


def _worded(error: Any) -> InitErrorDetails:
    """One error as pydantic said it; an unknown field that is a setting of the model
    says instead that it takes effect only at a restart, and where to set it."""
    loc, kind, message = error["loc"], error["type"], error["msg"]
    name = str(loc[0]) if loc else ""
    if kind == "extra_forbidden" and name in Settings.model_fields:
        kind, message = "restart_needed", restart_reason(name)
    escaped = message.replace("{", "{{").replace("}", "}}")
    return {"type": PydanticCustomError(kind, escaped), "loc": loc, "input": error["input"]}


class _Change(BaseModel):
    """The base of SettingsChange: strict about its keys, and says why a setting of the
    model that is not a runtime one is refused."""

    model_config = ConfigDict(extra="forbid", json_schema_extra=_without_defaults)

    @model_validator(mode="wrap")
    @classmethod
    def _say_restart(cls, value: Any, handler: ValidatorFunctionWrapHandler) -> Any:
        try:
            return handler(value)
        except ValidationError as exc:
            errors = exc.errors()
            if not any(e["type"] == "extra_forbidden" for e in errors):
                raise
            raise ValidationError.from_exception_data(
                exc.title, [_worded(e) for e in errors]
            ) from None


def _change_model() -> type[BaseModel]:
    fields: dict[str, Any] = {}
    for name in RUNTIME_SETTINGS:
        declared = Settings.model_fields[name]
        annotation = _strict(declared.annotation, declared.metadata)
        fields[name] = (annotation, Field(None, description=declared.description))
    return create_model(
        "SettingsChange",
        __base__=_Change,
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
