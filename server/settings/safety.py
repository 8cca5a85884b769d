"""The `SafetySettings` section of the settings. How long each step of a stop, a pause, a
reset and the move home may take (seconds).
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import Field

from server.settings.section import Section


class SafetySettings(Section):
    """How long each step of a stop, a pause, a reset and the move home may take (seconds)."""

    title: ClassVar[str] = "Safety"

    emergency_stop_timeout: float = Field(
        1.0, ge=0.05, le=10, description="seconds each device command of a software stop may take"
    )
    pause_hold_timeout: float = Field(
        2.0,
        ge=0.05,
        le=60,
        description="a pause must have the valve closed and the robot confirmed still "
        "within this; otherwise it is refused and the cell goes to ERROR (PAUSE_NOT_HELD)",
    )
    safe_position_timeout: float = Field(
        30.0, ge=0.1, le=600, description="seconds the move to the safe position may take"
    )
    planning_timeout: float = Field(
        10.0,
        ge=0.01,
        le=600,
        description="seconds a run may spend planning its path (PLANNING_TIMEOUT past it)",
    )
    error_state_timeout: float = Field(
        300.0, ge=1, le=86_400, description="seconds in ERROR before an alert is raised"
    )
    reset_probe_timeout: float = Field(
        2.0,
        ge=0.01,
        le=60,
        description="seconds a reset waits for every device's live answer (all at once); "
        "a device not answering in time refuses the reset, and the cell keeps taking "
        "e-stops and faults meanwhile",
    )
