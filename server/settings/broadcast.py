"""The `BroadcastSettings` section of the settings. The WebSocket live views (/ws): how
many, how buffered, how often pinged and fed. /ws is always served on the HTTP port,
whatever broadcast_port says.
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import Field

from server.settings.section import Section


class BroadcastSettings(Section):
    """The WebSocket live views (/ws): how many, how buffered, how often pinged and fed.
    /ws is always served on the HTTP port, whatever broadcast_port says.
    """

    title: ClassVar[str] = "Live views"

    broadcast_enabled: bool = Field(True, description="accepted, no effect: /ws is always served")
    broadcast_port: int = Field(
        8000, ge=1, le=65535, description="accepted, no effect: /ws is on the HTTP port (--port)"
    )
    max_broadcast_clients: int = Field(
        100, ge=1, le=100_000, description="live views (/ws) open at once, all tokens together"
    )
    max_broadcast_clients_per_token: int = Field(
        10,
        ge=1,
        le=100_000,
        description="live views (/ws) one token may hold open at once, so one token "
        "cannot take every slot",
    )
    broadcast_clients_reserved: int = Field(
        2,
        ge=0,
        le=100_000,
        description="of max_broadcast_clients, the slots only maintenance and admin may "
        "use (at most all but one)",
    )
    ws_client_buffer: int = Field(256, ge=8, le=100_000, description="messages queued per client")
    ws_ping_interval: float = Field(
        20.0, ge=1, le=600, description="seconds between pings of a /ws client; as long to answer"
    )
    device_push_interval: float = Field(
        0.1,
        ge=0.02,
        le=1,
        description="while an operation runs, a `device` message (valve, flow, pressure, "
        "robot position) is pushed on /ws at most this often; once a second otherwise",
    )
