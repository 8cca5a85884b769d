"""The Sparkplug B settings: the cell as an edge node on the plant's broker.

Off unless `sparkplug_group` is set. The node uses the broker of the MQTT link
(`mqtt_url`, its user, password and CA); it is a connection of its own there,
because Sparkplug's death certificate (NDEATH) must be that connection's last
will, and the MQTT link's will is its own `status` (docs/plant-integration.md,
"Sparkplug B").
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import Field, model_validator

from server.settings.section import Section

# Sparkplug ids are one topic level: no '/', '+' or '#' (and none of the MQTT wildcards).
SPARKPLUG_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$"
TOKEN_ID_PATTERN = r"^[0-9a-f]{8}$"


class SparkplugSettings(Section):
    """Where the cell shows itself to a Sparkplug B host, and whether it takes its commands:
    off unless sparkplug_group is set (docs/plant-integration.md, "Sparkplug B")."""

    title: ClassVar[str] = "Sparkplug B"

    sparkplug_group: str | None = Field(
        None,
        pattern=SPARKPLUG_ID_PATTERN,
        description="the Sparkplug B group id: the cell is an edge node under "
        "spBv1.0/<group>/... on the MQTT broker (mqtt_url); off when unset",
        json_schema_extra={
            "accepts": "letters, digits, '.', '_' and '-', 1 to 64, the first a letter or "
            "digit; or unset"
        },
    )
    sparkplug_edge_node: str | None = Field(
        None,
        pattern=SPARKPLUG_ID_PATTERN,
        description="the Sparkplug B edge node id; the cell id (cell_id) when unset",
        json_schema_extra={
            "default_text": "the cell id",
            "accepts": "letters, digits, '.', '_' and '-', 1 to 64, the first a letter or digit",
        },
    )
    sparkplug_command_token_id: str | None = Field(
        None,
        pattern=TOKEN_ID_PATTERN,
        description="accept Sparkplug DCMD commands (Command/Start and the like) as the "
        "token with this id: its role bounds them and the audit names it; revoking the "
        "token stops them. Off when unset: a DCMD carries no signature, so only a "
        "broker whose ACL lets the host alone write DCMD should be trusted with them",
        json_schema_extra={"accepts": "a token id (8 hex digits, GET /tokens), or unset"},
    )

    @model_validator(mode="after")
    def _needs_a_broker(self) -> SparkplugSettings:
        """A Sparkplug group names an edge node on the MQTT link's broker: without
        `mqtt_url` the node would have nowhere to go, which is refused at start."""
        if self.sparkplug_group is not None and getattr(self, "mqtt_url", "") is None:
            raise ValueError("sparkplug_group needs mqtt_url: the edge node uses its broker")
        return self
