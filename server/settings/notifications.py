"""The `WebhookSettings` section of the settings. Webhooks: where the cell posts its signed
notices, and how each is queued and retried (docs/plant-integration.md).
"""

from __future__ import annotations

from typing import ClassVar, Self
from urllib.parse import urlsplit

from pydantic import Field, field_validator, model_validator

from server.security import destinations
from server.settings.section import Section
from server.settings.webhooks import WebhookTarget, named


class WebhookSettings(Section):
    """Webhooks: where the cell posts its signed notices, and how each is queued and
    retried (docs/plant-integration.md).
    """

    title: ClassVar[str] = "Notifications"

    webhooks: list[WebhookTarget] = Field(
        default_factory=list,
        max_length=32,
        description="where the cell POSTs a signed JSON notice of a fault, an alert, a state "
        "change or a completed run: a JSON list of {name, url, events, secret or "
        "secret_file}; none by default",
        json_schema_extra={
            "accepts": 'a JSON list of objects such as {"url": "https://host/hook", '
            '"events": ["fault", "run_completed"], "secret_file": "/run/secrets/hook"} '
            "(events: fault, alert, state, run_completed, part, report; default all; a "
            "secret of at least 16 characters, inline or in a file)",
            "holds_secrets": True,
        },
    )
    webhook_allowed_networks: list[str] = Field(
        default_factory=list,
        max_length=256,
        description="networks (CIDR or address) a webhook may post to although the "
        "destination policy refuses them: loopback, link-local, unspecified and this host's "
        "own addresses are refused, at load and at each connection (docs/security.md); "
        "none by default",
    )
    webhook_queue_size: int = Field(
        100,
        ge=1,
        le=100_000,
        description="notices waiting per webhook; when full, the oldest is dropped "
        "(counted at GET /webhooks and journaled)",
    )
    webhook_timeout: float = Field(
        5.0, ge=0.1, le=120, description="seconds one delivery attempt may take (connect to answer)"
    )
    webhook_max_attempts: int = Field(
        5,
        ge=1,
        le=50,
        description="attempts per notice: a timeout, a connection error, 408, 429 or 5xx is "
        "retried; any other answer is final",
    )
    webhook_retry_delay: float = Field(
        1.0, ge=0.01, le=600, description="seconds before the first retry; doubled for each next"
    )
    webhook_retry_max_delay: float = Field(
        60.0,
        ge=0.01,
        le=3600,
        description="the longest wait between two attempts (a Retry-After included)",
    )

    @field_validator("webhooks")
    @classmethod
    def _webhooks_named(cls, value: list[WebhookTarget]) -> list[WebhookTarget]:
        return named(value)

    @field_validator("webhook_allowed_networks")
    @classmethod
    def _webhook_networks(cls, value: list[str]) -> list[str]:
        destinations.parse_networks(value)  # a typo refused at load, naming the entry
        return value

    @model_validator(mode="after")
    def _webhook_destinations(self) -> Self:
        """A webhook to the cell itself, loopback or link-local is refused at load, naming the
        webhook (never its path or query): the cell must not be made to post to itself."""
        allowed = destinations.parse_networks(self.webhook_allowed_networks)
        for target in self.webhooks:
            host = urlsplit(target.url).hostname or ""
            why = destinations.load_refusal(host, allowed)
            if why is not None:
                raise ValueError(
                    f"webhook {target.name!r} posts to {host}, {why}: refused by the webhook "
                    f"destination policy (add its network to {destinations.SETTING} to "
                    "allow it)"
                )
        return self
