"""The `RecordingSettings` section of the settings. The flight recorder of each run and the
shift reports.
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import Field

from server.settings.section import Section


class RecordingSettings(Section):
    """The flight recorder of each run and the shift reports."""

    title: ClassVar[str] = "Flight recorder and reports"

    run_recording: bool = Field(
        True,
        description="journal each run's device samples (pose, valve, flow, pressure, speed) "
        "at the live feed's rate, for GET /runs/{run_id}/recording",
    )
    run_recording_flush_s: float = Field(
        1.0,
        ge=0.1,
        le=60,
        description="seconds of a run's samples written to the journal together (one "
        "transaction); a run's end writes what is left at once",
    )
    shift_reports: bool = Field(
        True,
        description="make a report at the end of each shift and production day, kept in the "
        "journal (GET /reports) and sent by webhook (report) and MQTT (report topic)",
    )
    shift_start_hour: int = Field(
        6,
        ge=0,
        le=23,
        description="the local hour (whole) the production day's first shift starts; the day "
        "is cut into shifts of shift_hours from it",
    )
