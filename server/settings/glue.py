"""The `GlueSettings` section of the settings. The glue dispenser ("sim" starts the
simulator on loopback) and its supervision (docs/hardware.md says where each default
comes from).
"""

from __future__ import annotations

from typing import Annotated, ClassVar, Self
from urllib.parse import urlsplit

from pydantic import AliasChoices, Field, field_validator, model_validator

from server.settings.section import SIMULATED, Section

Psi = Annotated[float, Field(ge=0, le=150)]  # the dispenser's pressure register's span
Celsius = Annotated[float, Field(ge=-40, le=150)]


def parse_tcp_address(value: str) -> tuple[str, int]:
    """`tcp://host:port` → (host, port); ValueError naming the setting otherwise."""
    parts = urlsplit(value)
    try:
        port = parts.port
    except ValueError:  # past 65535
        port = None
    if parts.scheme != "tcp" or not parts.hostname or not port:
        raise ValueError(f"GLUE_CONTROLLER_PORT={value!r}: expected tcp://host:port")
    return parts.hostname, port


class GlueSettings(Section):
    """The glue dispenser ("sim" starts the simulator on loopback) and its supervision
    (docs/hardware.md says where each default comes from).
    """

    title: ClassVar[str] = "Glue dispenser"

    glue_controller_port: str = Field(
        SIMULATED,
        validation_alias=AliasChoices("glue_controller_port", "GLUE_CONTROLLER_PORT"),
        description="the dispenser's serial port (Modbus RTU) or tcp://host:port; sim: simulator",
    )
    glue_modbus_device_id: int = Field(1, ge=1, le=247, description="the dispenser's Modbus unit")
    glue_system_timeout: float = Field(
        15.0, ge=0.1, le=300, description="seconds for the glue dispenser to answer"
    )
    glue_pressure_range_psi: tuple[Psi, Psi] = Field(
        (20.0, 60.0),
        description="measured glue pressure above high PSI is a fault at any time, below low "
        "PSI while the valve is open (the dispenser's own alarms apply too); default: the "
        "default setpoint (default_pressure_psi, 40 PSI) +-50 %",
    )
    glue_flow_deviation_pct: float = Field(
        20.0,
        ge=1,
        le=100,
        description="while spraying, measured flow off its setpoint by more than this many "
        "percent for glue_flow_deviation_s is a fault",
    )
    glue_flow_deviation_s: float = Field(
        0.5,
        ge=0.05,
        le=10,
        description="how long a flow deviation may last (the valve's opening transient is "
        "shorter); 0.5 s is 50 mm of bead at the default spray speed",
    )
    glue_temperature_range_c: tuple[Celsius, Celsius] = Field(
        (10.0, 40.0),
        description="glue temperature outside [low, high] degC is a fault at any time; the "
        "default suits a room-temperature adhesive, set it for a heated one",
    )
    glue_link_timeout: float = Field(
        0.5,
        ge=0.05,
        le=5,
        description="a dispenser silent this long while its valve may be open is a fault at "
        "once (the valve could not be confirmed closed); must exceed glue_poll_interval",
    )
    glue_poll_interval: float = Field(
        0.1,
        ge=0.02,
        le=1,
        description="how often the dispenser's status is read (valve, flow, pressure, "
        "temperature, alarms)",
    )

    @property
    def glue_simulated(self) -> bool:
        return self.glue_controller_port == SIMULATED

    @field_validator("glue_controller_port")
    @classmethod
    def _glue_tcp_port(cls, value: str) -> str:
        """tcp://host:port (the network simulator, a serial server): checked at load, where a
        port past 65535 crashed the start and a missing one failed at the first connect."""
        if value.startswith("tcp://"):
            try:
                parse_tcp_address(value)
            except ValueError:
                raise ValueError("a TCP dispenser is tcp://HOST:PORT, PORT 1 to 65535") from None
        return value

    @field_validator("glue_pressure_range_psi")
    @classmethod
    def _ordered_range(cls, value: tuple[float, float]) -> tuple[float, float]:
        low, high = value
        if not 0 <= low < high <= 150:
            raise ValueError("glue_pressure_range_psi needs 0 <= low < high <= 150 PSI")
        return value

    @field_validator("glue_temperature_range_c")
    @classmethod
    def _ordered_temperatures(cls, value: tuple[float, float]) -> tuple[float, float]:
        low, high = value
        if not -40 <= low < high <= 150:
            raise ValueError("glue_temperature_range_c needs -40 <= low < high <= 150 degC")
        return value

    @model_validator(mode="after")
    def _link_outlasts_poll(self) -> Self:
        """A link timeout within one poll would trip on the dispenser's normal silence."""
        if self.glue_link_timeout <= self.glue_poll_interval:
            raise ValueError(
                f"glue_link_timeout ({self.glue_link_timeout:g} s) must exceed "
                f"glue_poll_interval ({self.glue_poll_interval:g} s)"
            )
        return self
