"""The `MotionSettings` section of the settings. Where the robot may go, how fast, and what
a run sprays with.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated, ClassVar, Self

from pydantic import Field, model_validator

from server.settings.section import Section

# Coordinates and angles in the robot's base frame. Why these bounds: a cell's robot
# reaches a metre or two; ten metres is a typo caught, not a cell refused.
Millimetres = Annotated[float, Field(ge=-10_000, le=10_000)]
Degrees = Annotated[float, Field(ge=-360, le=360)]


def outside_workspace(
    point: Sequence[float], low: Sequence[float], high: Sequence[float]
) -> str | None:
    """Which axis of `point` (x, y, z mm; more is ignored) leaves [low, high], or None."""
    for axis, value, lo, hi in zip("xyz", point[:3], low, high, strict=True):
        if not lo <= value <= hi:
            return f"{axis}={value:.1f} mm, allowed {lo:.0f}..{hi:.0f} mm"
    return None


class MotionSettings(Section):
    """Where the robot may go, how fast, and what a run sprays with."""

    title: ClassVar[str] = "Cell geometry and motion"

    safe_position: tuple[Millimetres, Millimetres, Millimetres, Degrees, Degrees, Degrees] = Field(
        (400.0, 0.0, 200.0, 180.0, 0.0, 0.0),
        description="where `home` sends the robot: x, y, z mm (inside the workspace) and rx, "
        "ry, rz degrees",
    )
    spray_height_mm: float = Field(20.0, ge=0, le=500, description="nozzle height over the part")
    travel_speed_mm_s: float = Field(250.0, ge=1, le=2000, description="mm/s between beads")
    spray_speed_mm_s: float = Field(100.0, ge=1, le=2000, description="mm/s along a bead")
    acceleration_mm_s2: float = Field(1000.0, ge=10, le=20000, description="mm/s² of every move")
    default_flow_rate_ml_min: float = Field(
        30.0,
        ge=0,
        le=1000,
        description="ml/min; accepted, no effect: each workpiece's spray settings set the flow",
    )
    default_pressure_psi: float = Field(
        40.0,
        ge=0,
        le=150,
        description="PSI pressure setpoint of every run; inside glue_pressure_range_psi",
    )
    workspace_min_mm: tuple[Millimetres, Millimetres, Millimetres] = Field(
        (100.0, -400.0, -5.0),
        description="x, y, z mm: no move goes below these; each below workspace_max_mm",
    )
    workspace_max_mm: tuple[Millimetres, Millimetres, Millimetres] = Field(
        (800.0, 400.0, 500.0), description="x, y, z mm: no move goes above these"
    )
    jog_max_step_mm: float = Field(
        50.0,
        ge=0.1,
        le=200,
        description="the longest step one jog may ask for along its axis (maintenance "
        "teaching marker positions); a longer one is refused before anything moves",
    )
    jog_speed_mm_s: float = Field(
        20.0,
        ge=1,
        le=250,
        description="speed of a jog: slow, so a person beside the table can follow the arm",
    )

    @model_validator(mode="after")
    def _workspace_ordered(self) -> Self:
        """An empty workspace would refuse every move with a message about the move."""
        for axis, low, high in zip(
            "xyz", self.workspace_min_mm, self.workspace_max_mm, strict=True
        ):
            if not low < high:
                raise ValueError(
                    f"workspace_min_mm must be below workspace_max_mm on every axis; "
                    f"{axis}: {low:g} is not below {high:g}"
                )
        return self

    @model_validator(mode="after")
    def _safe_position_inside(self) -> Self:
        """Every run's first move and `home` go to the safe position: outside the workspace,
        `home` was refused and every run accepted, then failed with WORKSPACE_VIOLATION."""
        problem = outside_workspace(
            self.safe_position, self.workspace_min_mm, self.workspace_max_mm
        )
        if problem is not None:
            raise ValueError(
                f"safe_position is outside the workspace ({problem}; workspace_min_mm, "
                "workspace_max_mm)"
            )
        return self
