"""The `QualitySettings` section of the settings. Each part inspected, and production
orders (docs/quality.md).
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import Field

from server.settings.section import Section


class QualitySettings(Section):
    """Each part inspected, and production orders (docs/quality.md)."""

    title: ClassVar[str] = "Quality"

    inspection_enabled: bool = Field(
        True,
        description="after each completed spray run, measure the run and inspect the part's "
        "bead (GET /runs/{id}/inspection); off: runs are neither judged nor counted as parts",
    )
    quality_sample_interval_s: float = Field(
        0.05,
        ge=0.01,
        le=1,
        description="while spraying, the robot's position and the dispenser's flow are read "
        "this often for the run's trajectory precision and dispensing consistency",
    )
    trajectory_precision_limit_mm: float = Field(
        1.0,
        ge=0.01,
        le=50,
        description="a part is defective when the robot strayed further than this (mm) from "
        "a spray segment",
    )
    dispensing_flow_tolerance_percent: float = Field(
        10.0,
        ge=0.1,
        le=100,
        description="flow further than this (%) from its setpoint counts as out of tolerance",
    )
    dispensing_max_out_of_tolerance_s: float = Field(
        0.5,
        ge=0,
        le=60,
        description="a part is defective when its flow was out of tolerance longer than this "
        "(s) while spraying",
    )
    glue_volume_tolerance_percent: float = Field(
        20.0,
        ge=0.1,
        le=100,
        description="a part is defective when the glue dispensed differs from what its path "
        "needs (flow setpoint × length / speed) by more than this (%): wider than the flow's "
        "tolerance, as the arm stands still a few ms at each waypoint with the valve open",
    )
    bead_width_tolerance_percent: float = Field(
        30.0,
        ge=0.1,
        le=100,
        description="a bead narrower or wider than expected (from flow over speed) by more "
        "than this (%) is a defect",
    )
    bead_max_gap_mm: float = Field(
        3.0, ge=0.1, le=100, description="longest stretch of a spray segment without bead (mm)"
    )
    bead_max_offset_mm: float = Field(
        1.5,
        ge=0.1,
        le=50,
        description="furthest the bead's centre may lie from its planned path on the part (mm)",
    )
    order_defect_limit: int = Field(
        3,
        ge=1,
        le=1000,
        description="defective parts in a row that stop an order and the cell: a nozzle or "
        "a calibration is wrong, and more parts would be scrap",
    )
