"""What a command reads and what it answers, as strict pydantic models.

Requests refuse unknown fields and bound every value, so a typo in a script
("contourMatching") is a 422 naming the field instead of a silently ignored
option. Every transport checks a command's body with the model its catalogue
entry names (server/commands/catalogue.py), so a body is refused alike whichever
way it came.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, StrictBool

from server.common.values import FiniteNumber, Name
from server.storage.workpieces import IDENTIFIER, SpraySettingsIn


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class StartRequest(Strict):
    """Body of POST /start (all fields optional).

    Without contour matching, `workpiece_id` is required: the cell refuses the start
    otherwise (422 naming it). The schema states that rule for validators as an
    `if`/`then` beside the two typed properties, which generators that do not read
    conditionals pass over: they still model the body as its two typed fields.
    """

    model_config = ConfigDict(
        json_schema_extra={
            "if": {
                "required": ["contour_matching"],
                "properties": {"contour_matching": {"const": False}},
            },
            "then": {
                "required": ["workpiece_id"],
                "properties": {"workpiece_id": {"type": "string"}},
            },
        }
    )

    contour_matching: StrictBool = Field(
        True, description="find the workpiece in a fresh frame and match it to the library"
    )
    workpiece_id: str | None = Field(
        None, pattern=IDENTIFIER, description="spray this library workpiece"
    )


class CreateWorkpieceRequest(Strict):
    """Body of POST /create-workpiece (optional)."""

    name: Name | None = None
    workpiece_id: str | None = Field(
        None, pattern=IDENTIFIER, description="store under this id (default: the next wp-NNNN)"
    )
    spray: SpraySettingsIn | None = None


class JogRequest(Strict):
    """Body of POST /jog: one step along one axis of the robot's base frame."""

    axis: Literal["x", "y", "z"] = Field(description="the axis to move along")
    distance_mm: FiniteNumber = Field(
        ge=-200,
        le=200,
        description="the step in mm, negative to go back, never 0; at most jog_max_step_mm "
        "either way (GET /calibration/markers shows it), and the target must lie in the "
        "workspace",
        json_schema_extra={"not": {"const": 0}},
    )


class EstopRequest(Strict):
    """Body of POST /estop (optional): why the stop was pressed, for the record."""

    reason: str | None = Field(None, max_length=200)


class CommandResult(BaseModel):
    """The worker's decision on a command: 202 when accepted, 409 when refused."""

    accepted: bool
    event_id: str | None = Field(None, description="the event's id in logs and the journal")
    state: str = Field(description="the state after the decision")
    message: str
    run_id: str | None = Field(
        None,
        description="the run this command started (as in /trajectory, /operations, "
        "/camera/frame?run_id=, the logs); null when it started none",
    )


RETRY_AFTER_S = 1  # what a 503 (QueueFullResult) asks the client to wait


class QueueFullResult(BaseModel):
    """503: the event queue is full, or the journal cannot write (the message says which);
    retry after `retry_after` seconds."""

    accepted: bool = False
    event_id: str | None = Field(
        None, description="a command decided but not journaled: its event id (see `message`)"
    )
    state: str
    message: str
    retry_after: int
