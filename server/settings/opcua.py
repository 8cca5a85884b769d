"""The `OpcUaSettings` section of the settings. The OPC UA server (PackML tags, methods):
off unless opcua_endpoint is set (docs/plant-integration.md).
"""

from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import Field, field_validator

from server.settings.section import Section

# opc.tcp://host:port with an explicit port (a server must say where it listens).
OPCUA_ENDPOINT_PATTERN = r"^opc\.tcp://[A-Za-z0-9._:\[\]-]+:[0-9]{1,5}/?$"


class OpcUaSettings(Section):
    """The OPC UA server (PackML tags, methods): off unless opcua_endpoint is set
    (docs/plant-integration.md).
    """

    title: ClassVar[str] = "OPC UA"

    opcua_endpoint: str | None = Field(
        None,
        pattern=OPCUA_ENDPOINT_PATTERN,
        description="serve OPC UA (PackML tags, methods) at this endpoint, e.g. "
        "opc.tcp://0.0.0.0:4840; off if unset",
        json_schema_extra={"accepts": "opc.tcp://HOST:PORT (PORT 1 to 65535), or unset"},
    )
    opcua_allow_unsecured: bool = Field(
        True,
        description="also offer OPC UA security policy None (a lab); Basic256Sha256 Sign and "
        "SignAndEncrypt are always offered",
    )
    opcua_log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = Field(
        "WARNING",
        description="the level of asyncua's own loggers (the OPC UA library) in the cell's "
        "log: WARNING keeps its INFO lines (every node loaded, every request) out; DEBUG or "
        "INFO to trace a protocol problem",
    )
    opcua_admin_interval: float = Field(
        5.0,
        ge=1,
        le=3600,
        description="seconds between refreshes of the OPC UA Admin figures (KPIs of the shift)",
    )

    @field_validator("opcua_endpoint")
    @classmethod
    def _opcua_port(cls, value: str | None) -> str | None:
        """The pattern takes five digits; a port past 65535 is refused here, at load."""
        if value is not None and not 1 <= int(value.rstrip("/").rsplit(":", 1)[1]) <= 65535:
            raise ValueError("the OPC UA endpoint's port must be 1 to 65535")
        return value
