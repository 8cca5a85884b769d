"""How much of asyncua's own logging reaches the cell's log (server/opcua/server_info.py)."""

from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import BaseModel, Field


class OpcUaLoggingSettings(BaseModel):
    """The OPC UA library's log level, apart from the cell's own."""

    # The section of docs/settings.md it belongs to (server/settings/reference.py).
    settings_section: ClassVar[str] = "The plant's interfaces (docs/plant-integration.md)"

    opcua_log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = Field(
        "WARNING",
        description="the level of asyncua's own loggers (the OPC UA library) in the cell's "
        "log: WARNING keeps its INFO lines (every node loaded, every request) out; DEBUG or "
        "INFO to trace a protocol problem",
    )
