"""The `AccessSettings` section of the settings. Who may connect and how far a client is
believed; guessing of tokens and the audit of refusals (docs/security.md).
"""

from __future__ import annotations

import ipaddress
from typing import ClassVar, Literal

from pydantic import Field, field_validator

from server.settings.section import Section


class AccessSettings(Section):
    """Who may connect and how far a client is believed; guessing of tokens and the audit
    of refusals (docs/security.md).
    """

    title: ClassVar[str] = "Access"

    trusted_networks: list[str] = Field(
        default_factory=list, description="if set, only clients from these networks (CIDR)"
    )
    trusted_proxies: list[str] = Field(
        default_factory=list,
        max_length=256,
        description="proxies (CIDR or address) whose forwarded_header is believed; none by "
        "default: the client is the peer, whatever a request's headers say",
    )
    forwarded_header: Literal["x-forwarded-for", "forwarded"] = Field(
        "x-forwarded-for",
        description="the header the trusted_proxies set (X-Forwarded-For or RFC 7239 "
        "Forwarded); the other one is never read",
    )
    cors_allowed_origins: list[str] = Field(default_factory=list, description="closed if empty")
    max_request_bytes: int = Field(
        1024 * 1024, ge=1024, le=64 * 1024 * 1024, description="largest request body, bytes"
    )
    auth_failure_limit: int = Field(
        20,
        ge=1,
        le=10_000,
        description="bad tokens or tickets from one address within auth_failure_window "
        "that lock it out (429 with Retry-After; never the e-stop)",
    )
    auth_failure_window: float = Field(
        60.0, ge=1, le=86_400, description="seconds over which auth_failure_limit is counted"
    )
    auth_lockout_s: float = Field(
        60.0, ge=1, le=86_400, description="seconds a locked-out address is answered 429"
    )
    audit_repeat_window: float = Field(
        60.0,
        ge=1,
        le=3600,
        description="seconds within which identical refusals (same who, address, action, "
        "outcome and reason) are one audit row with a count",
    )

    @field_validator("trusted_proxies")
    @classmethod
    def _proxy_networks(cls, value: list[str]) -> list[str]:
        """A typo here would silently trust nobody (or the wrong host): refuse it at load."""
        for entry in value:
            try:
                ipaddress.ip_network(entry.strip(), strict=False)
            except ValueError:
                raise ValueError(
                    f"trusted_proxies: {entry!r} is not an IP address or network (CIDR)"
                ) from None
        return value
