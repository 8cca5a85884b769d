"""The `MqttSettings` section of the settings. The link to the plant's MQTT broker: off
unless mqtt_url is set (docs/plant-integration.md).
"""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar
from urllib.parse import urlsplit

from pydantic import Field, SecretStr, field_validator

from server.settings.section import Section

MQTT_URL_PATTERN = r"^mqtts?://[^\s/:@]+(:[0-9]{1,5})?/?$"
# One or more topic levels: no wildcards, no empty level, no leading '$' (the broker's own).
MQTT_PREFIX_PATTERN = r"^[A-Za-z0-9._-]{1,64}(/[A-Za-z0-9._-]{1,64}){0,7}$"


class MqttSettings(Section):
    """The link to the plant's MQTT broker: off unless mqtt_url is set
    (docs/plant-integration.md).
    """

    title: ClassVar[str] = "MQTT"

    mqtt_url: str | None = Field(
        None,
        pattern=MQTT_URL_PATTERN,
        description="the plant's MQTT broker, mqtt://host:1883 or mqtts://host:8883; "
        "off when unset",
        json_schema_extra={"accepts": "mqtt://host[:port] or mqtts://host[:port]"},
    )
    mqtt_ca_file: Path | None = Field(
        None, description="CA certificate (PEM) the broker's is checked against (mqtts://)"
    )
    mqtt_username: str | None = Field(
        None, max_length=256, description="user name at the broker, if it asks for one"
    )
    mqtt_password: SecretStr | None = Field(
        None,
        description="password at the broker; never logged, shown as ********** by GET /settings",
    )
    mqtt_topic_prefix: str = Field(
        "glue",
        pattern=MQTT_PREFIX_PATTERN,
        description="first topic level(s): <prefix>/<cell_id>/state and the like",
        json_schema_extra={"accepts": "topic levels of letters, digits, '.', '_', '-', '/'"},
    )
    mqtt_keepalive: int = Field(
        30,
        ge=1,
        le=3600,
        description="seconds of MQTT keep-alive: the broker publishes the last will "
        "(status offline) after 1.5 times this without a word from the cell",
    )
    mqtt_buffer: int = Field(
        1000,
        ge=1,
        le=1_000_000,
        description="event, progress and alert messages kept while the broker is away; the "
        "oldest are dropped beyond it (counted in /health); retained topics keep their latest",
    )
    mqtt_reconnect_max: float = Field(
        30.0,
        ge=0.1,
        le=600,
        description="longest wait between reconnection attempts, seconds (from 0.1 s, doubling)",
    )
    mqtt_kpis_interval: float = Field(
        10.0,
        ge=1,
        le=3600,
        description="seconds between publications of the retained KPIs (also after each run ends)",
    )
    mqtt_health_interval: float = Field(
        10.0,
        ge=1,
        le=3600,
        description="seconds between publications of the retained health (also on a change)",
    )
    mqtt_commands: bool = Field(
        False,
        description="accept commands on <prefix>/<cell_id>/command/<name>, each signed with "
        "a token (same roles as HTTP); off by default",
    )
    mqtt_command_max_age: float = Field(
        30.0,
        ge=1,
        le=600,
        description="seconds a signed MQTT command stays valid after its ts_ms; an older one "
        "is refused as stale (and its nonce need only be remembered this long)",
    )
    mqtt_command_max_skew: float = Field(
        5.0,
        ge=0,
        le=60,
        description="seconds a signed MQTT command's ts_ms may be ahead of the cell's clock "
        "(the sender's clock running fast); further ahead is refused",
    )

    @field_validator("mqtt_url")
    @classmethod
    def _mqtt_port(cls, value: str | None) -> str | None:
        """The pattern takes five digits: 99999 crashed the start, 0 meant 1883 silently."""
        try:
            port = urlsplit(value).port if value else None
        except ValueError:  # past 65535
            port = 0
        if port is not None and not 1 <= port <= 65535:
            raise ValueError("the broker's port must be 1 to 65535")
        return value
