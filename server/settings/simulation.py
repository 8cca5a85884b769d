"""The `SimulationSettings` section of the settings. The simulated cell: whether it is
commissioned at start and how fast it runs.
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import Field

from server.settings.section import Section


class SimulationSettings(Section):
    """The simulated cell: whether it is commissioned at start and how fast it runs."""

    title: ClassVar[str] = "Simulation"

    commission_simulated_cell: bool = Field(
        True, description="calibrate a fresh simulated cell and put its demo part in the library"
    )
    simulation_speed_factor: float = Field(
        1.0, ge=0.1, le=1000, description="simulated devices run this many times faster"
    )
