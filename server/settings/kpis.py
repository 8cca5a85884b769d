"""The `KpiSettings` section of the settings. The window and the ideal cycle time the KPIs
(OEE) are computed with.
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import Field

from server.settings.section import Section


class KpiSettings(Section):
    """The window and the ideal cycle time the KPIs (OEE) are computed with."""

    title: ClassVar[str] = "KPIs"

    shift_hours: float = Field(
        8.0, ge=0.25, le=24 * 31, description="hours of the default KPI window"
    )
    design_cycle_time_s: float = Field(
        30.0, ge=0.1, le=3600, description="ideal time of one trajectory run, for OEE performance"
    )
