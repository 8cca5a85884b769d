"""The `PlantSettings` section of the settings. What names the cell to the plant and how
often a run's progress reaches it (docs/plant-integration.md).
"""

from __future__ import annotations

import re
import socket
from typing import ClassVar

from pydantic import Field

from server.settings.section import Section

# A cell id is one MQTT topic level and an OPC UA browse name: no '/', '+', '#', spaces.
CELL_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$"


def default_cell_id() -> str:
    """The host name, made a valid cell id (other characters become '-')."""
    name = re.sub(r"[^A-Za-z0-9._-]", "-", socket.gethostname()).strip("-.") or "cell"
    return name[:64] if name[0].isalnum() else f"cell-{name}"[:64]


class PlantSettings(Section):
    """What names the cell to the plant and how often a run's progress reaches it
    (docs/plant-integration.md).
    """

    title: ClassVar[str] = "The plant's interfaces"

    cell_id: str = Field(
        default_factory=lambda: default_cell_id(),
        pattern=CELL_ID_PATTERN,
        description="names this cell to the plant: its OPC UA object and its MQTT topics "
        "(glue/<cell_id>/...)",
        json_schema_extra={
            "default_text": "the host name",
            "accepts": "letters, digits, '.', '_' and '-', 1 to 64, the first a letter or digit",
        },
    )
    plant_progress_interval: float = Field(
        0.25,
        ge=0,
        le=10,
        description="a run's progress reaches the plant (OPC UA CellState, MQTT progress) at "
        "most this often, in seconds, the latest kept; transitions are never held and a "
        "run's final progress goes before the transition that ends it; 0: every waypoint",
    )
