"""The `MaintenanceSettings` section: wear counters, the maintenance schedule and the
glue line's care (purge, pot life, reservoir level). docs/operations-guide.md,
"Maintenance", says how a technician uses them.
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import Field, field_validator

from server.settings.motion import Degrees, Millimetres
from server.settings.section import Section


class MaintenanceItem(Section):
    """One maintenance task and its intervals: due when any interval is used up (100 %);
    an item with none is listed and never due (a schema alone cannot say "at least one
    of these", so a client that builds items from openapi.json is not refused for it)."""

    title: ClassVar[str] = "Maintenance item"

    name: str = Field(
        min_length=1,
        max_length=60,
        pattern=r"^[A-Za-z0-9][A-Za-z0-9 _.-]*$",
        description="the task, e.g. clean nozzle",
    )
    every_parts: int | None = Field(None, ge=1, le=10**9, description="parts sprayed")
    every_ml: float | None = Field(None, ge=0.001, le=1e9, description="glue dispensed, ml")
    every_valve_cycles: int | None = Field(None, ge=1, le=10**12, description="valve openings")
    every_valve_open_hours: float | None = Field(
        None, ge=0.001, le=1e6, description="valve open, hours"
    )
    every_travel_m: float | None = Field(None, ge=0.001, le=1e9, description="robot travel, metres")
    every_motion_hours: float | None = Field(
        None, ge=0.001, le=1e6, description="robot moving, hours"
    )
    every_camera_frames: int | None = Field(None, ge=1, le=10**12, description="camera frames")
    every_purges: int | None = Field(None, ge=1, le=10**9, description="purges")

    def intervals(self) -> dict[str, float]:
        """Its intervals by counter name (the wear meter's), hours as seconds."""
        hours = {"every_valve_open_hours": "valve_open_s", "every_motion_hours": "motion_s"}
        counters = {
            "every_parts": "parts",
            "every_ml": "glue_ml",
            "every_valve_cycles": "valve_cycles",
            "every_travel_m": "travel_m",
            "every_camera_frames": "camera_frames",
            "every_purges": "purges",
        }
        found: dict[str, float] = {}
        for field, counter in counters.items():
            if (value := getattr(self, field)) is not None:
                found[counter] = float(value)
        for field, counter in hours.items():
            if (value := getattr(self, field)) is not None:
                found[counter] = float(value) * 3600.0
        return found


DEFAULT_ITEMS = (
    MaintenanceItem(name="clean nozzle", every_parts=200, every_ml=500.0),
    MaintenanceItem(name="service valve", every_valve_cycles=1_000_000),
)


class MaintenanceSettings(Section):
    """Wear counters, the maintenance schedule and the glue line's care."""

    title: ClassVar[str] = "Maintenance and glue line"

    maintenance_items: tuple[MaintenanceItem, ...] = Field(
        DEFAULT_ITEMS,
        description="the maintenance schedule: each item a name and one or more every_* "
        "intervals (parts, ml, valve_cycles, valve_open_hours, travel_m, motion_hours, "
        "camera_frames, purges); due at 100 % of any interval, overdue past "
        "maintenance_overdue_percent",
    )
    maintenance_overdue_percent: float = Field(
        120.0, ge=100, le=1000, description="an item is overdue past this share of its interval"
    )
    wear_persist_interval: float = Field(
        30.0,
        ge=1,
        le=3600,
        description="seconds between writes of the wear counters to the journal (also at "
        "each run's end and at a clean stop)",
    )
    care_check_interval: float = Field(
        1.0,
        ge=0.1,
        le=60,
        description="seconds between reads of the drivers' counters and checks of the "
        "schedule, the pot life and the glue level",
    )
    purge_position: tuple[Millimetres, Millimetres, Millimetres, Degrees, Degrees, Degrees] = Field(
        (400.0, 0.0, 150.0, 180.0, 0.0, 0.0),
        description="where `purge` sends the nozzle (over the purge cup): x, y, z mm (inside "
        "the workspace, checked before anything moves) and rx, ry, rz degrees",
    )
    purge_seconds: float = Field(
        3.0, ge=0.1, le=120, description="how long `purge` holds the valve open"
    )
    purge_flow_ml_min: float = Field(
        60.0, ge=0.1, le=1000, description="the flow setpoint of a purge, ml/min"
    )
    pot_life_minutes: float | None = Field(
        None,
        ge=0.01,
        le=10080,
        description="the adhesive's pot life (open time) since the last dispense: a start "
        "after it is refused until a purge; off if unset",
    )
    pot_life_warning_percent: float = Field(
        80.0, ge=1, le=99, description="warn once this share of the pot life has passed"
    )
    glue_reservoir_ml: float | None = Field(
        None,
        ge=1,
        le=1_000_000,
        description="the reservoir's volume when full: the level is estimated from the glue "
        "dispensed since the last refill; off if unset",
    )
    glue_low_level_percent: float = Field(
        15.0, ge=1, le=99, description="warn when the estimated level falls to this share"
    )

    @field_validator("maintenance_items")
    @classmethod
    def _unique_names(cls, items: tuple[MaintenanceItem, ...]) -> tuple[MaintenanceItem, ...]:
        names = [item.name.lower() for item in items]
        if len(set(names)) != len(names):
            raise ValueError("maintenance item names must be unique")
        return items
