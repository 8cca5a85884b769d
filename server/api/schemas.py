"""Every message the HTTP API reads or writes, as strict pydantic models.

Requests refuse unknown fields and bound every value, so a typo in a script
("contourMatching") is a 422 naming the field instead of a silently ignored
option.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

# The commands' own messages live with the catalogue; named here too, as the API's.
from server.api.watch import SystemHealthView
from server.commands.requests import (  # noqa: F401
    RETRY_AFTER_S,
    CommandResult,
    CreateWorkpieceRequest,
    EstopRequest,
    JogRequest,
    QueueFullResult,
    StartRequest,
    Strict,
)


def binary_body(media_type: str) -> dict[str, Any]:
    """A response's `content` of raw bytes (an image) as OpenAPI states it: a binary
    string, which client generators turn into a file rather than leave out."""
    return {media_type: {"schema": {"type": "string", "format": "binary"}}}


def text_body(media_type: str) -> dict[str, Any]:
    """A response's `content` of text (CSV, Prometheus text): a string to generators."""
    return {media_type: {"schema": {"type": "string"}}}


class OperationView(BaseModel):
    name: str
    run_id: str
    progress: dict[str, Any] | None = None


class FaultView(BaseModel):
    code: str
    message: str
    component: str
    event_id: str
    time: float
    classification: str = Field(description="critical, recoverable or warning")
    recommended_action: str = Field(description="what the technician should do first")


class StateView(BaseModel):
    """GET /state."""

    state: str
    previous_state: str | None
    since: float = Field(description="Unix time the current state was entered")
    time_in_state: float = Field(description="seconds in the current state")
    operation: OperationView | None
    error: FaultView | None = Field(description="the latest fault while in ERROR")
    stop_reason: FaultView | None = Field(description="first-out: the fault that stopped the cell")
    available_commands: list[str] = Field(description="the commands the current state allows")
    may: list[str] | None = Field(
        None,
        description="of those, the ones the caller's token may send (its role allows them): "
        "what a page offers this user now",
    )
    operation_result: dict[str, Any] | None = None


class AllowedView(BaseModel):
    """GET /operations/{name}/allowed."""

    operation: str
    allowed: bool
    state: str
    reason: str


class DeviceView(BaseModel):
    model_config = ConfigDict(extra="allow")

    connected: bool
    last_rtt_ms: float | None = None
    last_error: str | None = None
    last_ok_at: float | None = None
    active_faults: list[str] = Field(
        default_factory=list, description="conditions the device reports as persisting now"
    )


class PerformanceView(BaseModel):
    events_processed: int
    events_refused: int
    average_processing_time_ms: float
    p99_processing_time_ms: float
    queue_size: int


class JournalDamageView(BaseModel):
    """One thing start-up found wrong with the journal (also logged CRITICAL and recorded
    in the journal's errors as JOURNAL_DAMAGED)."""

    message: str = Field(description="what is wrong, what was lost, what was done")
    first_commit: int | None = Field(None, description="the first commit concerned, if known")
    last_commit: int | None = Field(None, description="the last commit concerned, if known")
    missing_rows: dict[str, int] = Field(
        default_factory=dict, description="rows lost per table, e.g. {'transitions': 8}"
    )
    kept_as: str | None = Field(
        None, description="the file, beside the journal, the damaged journal was kept as"
    )
    found_at: float = Field(description="when start-up found it (Unix time)")


class JournalHealthView(BaseModel):
    """The journal: what waits for the disk, the last write that failed, the damage found."""

    backlog: int = Field(description="records queued for the disk")
    last_error: str | None = Field(
        None, description="the last write failure, None once a later write succeeded"
    )
    last_error_at: float | None = Field(None, description="when it failed (Unix time)")
    damage: list[JournalDamageView] = Field(
        default_factory=list,
        description="what start-up found wrong with the journal; empty when nothing; "
        "kept until the server stops",
    )


class MqttHealthView(BaseModel):
    """The MQTT link (docs/plant-integration.md)."""

    connected: bool
    broker: str = Field(description="the broker's host and port")
    since: float | None = Field(description="Unix time the link last came up or went down")
    buffered: int = Field(description="messages waiting for the broker")
    dropped: int = Field(
        description="event, progress and alert messages dropped since start (the buffer, "
        "mqtt_buffer, was full while the broker was away)"
    )
    reconnects: int = Field(description="connections made after the first")
    last_error: str | None = Field(description="why the link last went down")
    commands: bool = Field(description="whether commands are accepted over MQTT")


class HealthView(BaseModel):
    """GET /health: ok when every device answers, degraded otherwise."""

    status: str
    state: str
    devices: dict[str, DeviceView]
    worker: PerformanceView
    journal: JournalHealthView
    websocket_clients: int
    mqtt: MqttHealthView | None = Field(None, description="the MQTT link, when mqtt_url is set")
    system: SystemHealthView | None = Field(
        None, description="the cell's own resources, link trends and error rate"
    )


class ErrorView(BaseModel):
    detail: str


FRAME_RETRY_AFTER_S = 1  # what a 409 of GET /camera/frame?run_id= asks the client to wait


class FramePendingView(BaseModel):
    """409: the run asked for is under way and has not captured its frame yet (it may
    never: a trajectory run without contour matching captures none); retry after
    `retry_after` seconds, as the Retry-After header says."""

    detail: str
    run_id: str
    retry_after: int
