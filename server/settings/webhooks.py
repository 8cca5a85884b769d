"""One configured webhook: where it posts, which kinds of notice, and its secret.

Why the secret may come from a file (`secret_file`) as well as inline (`secret`):
the webhooks are one JSON setting (GLUE_APP_WEBHOOKS or the config file), and a
secret inline sits in the process's environment, which `docker inspect`, a
systemd unit's Environment= or /proc/<pid>/environ show to more people than
need it. A file readable by the cell's user alone (a Docker or systemd
credential) keeps it out of all of them. Inline stays accepted for a lab.
Either way it is held as a SecretStr: GET /settings, GET /webhooks and the logs
never show it, nor a refused setting's value (server/settings/load.py).

Why the URL is shown only as scheme://host:port: many receivers (chat services,
automation tools) put their own token in the path or the query, so the URL is a
secret too.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal
from urllib.parse import urlsplit

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    SecretStr,
    field_serializer,
    field_validator,
    model_validator,
)

from server.security.redaction import shown_url

NoticeKind = Literal["fault", "alert", "state", "run_completed", "part", "report"]
NOTICE_KINDS: tuple[NoticeKind, ...] = (
    "fault",
    "alert",
    "state",
    "run_completed",
    "part",
    "report",
)
WEBHOOK_NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$"
MIN_SECRET_LENGTH = 16  # characters: a guessable HMAC key signs nothing
MAX_SECRET_BYTES = 4096


class WebhookTarget(BaseModel):
    """One entry of the `webhooks` setting."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str | None = Field(
        None,
        pattern=WEBHOOK_NAME_PATTERN,
        description="names it in the journal and at GET /webhooks (default webhook-<n>)",
    )
    url: str = Field(description="http:// or https:// URL the notices are POSTed to")
    events: list[NoticeKind] = Field(
        default_factory=lambda: list(NOTICE_KINDS),
        min_length=1,
        description="which notices: fault, alert, state, run_completed, part, report (default all)",
    )
    secret: SecretStr | None = Field(
        None, description=f"the HMAC-SHA256 key, at least {MIN_SECRET_LENGTH} characters"
    )
    secret_file: Path | None = Field(
        None, description="a file holding the key instead (read at start, stripped)"
    )
    _file_secret: str | None = PrivateAttr(None)

    @field_validator("url")
    @classmethod
    def _an_http_url(cls, value: str) -> str:
        """Refused at load, not at the first fault: a typo here means nobody is told."""
        parts = urlsplit(value)
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise ValueError("a webhook url must be http:// or https:// with a host")
        if parts.username is not None or parts.password is not None:
            raise ValueError("a webhook url must not carry a user or password (use the secret)")
        if parts.fragment:
            raise ValueError("a webhook url has no #fragment (it is never sent)")
        try:
            parts.port  # noqa: B018 (raises on a port out of range)
        except ValueError as exc:
            raise ValueError(f"a webhook url's port is invalid: {exc}") from None
        return value

    @field_validator("events")
    @classmethod
    def _each_once(cls, value: list[NoticeKind]) -> list[NoticeKind]:
        return list(dict.fromkeys(value))

    @model_validator(mode="after")
    def _one_secret(self) -> WebhookTarget:
        """Every delivery is signed: exactly one of secret and secret_file."""
        if (self.secret is None) == (self.secret_file is None):
            raise ValueError("a webhook needs exactly one of secret and secret_file")
        if self.secret_file is not None:
            self._file_secret = _read_secret(self.secret_file)
        elif len(self.secret_value) < MIN_SECRET_LENGTH:
            raise ValueError(f"a webhook secret needs at least {MIN_SECRET_LENGTH} characters")
        return self

    @property
    def secret_value(self) -> str:
        """The key (never log it, never show it)."""
        if self._file_secret is not None:
            return self._file_secret
        assert self.secret is not None
        return self.secret.get_secret_value()

    @property
    def shown_url(self) -> str:
        return shown_url(self.url)

    def __repr_args__(self) -> Iterator[tuple[str | None, Any]]:
        """Its repr and str (a Settings repr, a traceback's locals) show the URL as shown."""
        for name, value in super().__repr_args__():
            yield name, shown_url(value) if name == "url" else value

    @field_serializer("url", when_used="json")
    def _url_shown(self, value: str) -> str:
        return shown_url(value)

    def public(self) -> dict[str, Any]:
        """What GET /webhooks shows of it: nothing secret."""
        return {
            "name": self.name,
            "url": self.shown_url,
            "events": list(self.events),
            "secret_from": "secret_file" if self.secret_file is not None else "secret",
        }


def _read_secret(path: Path) -> str:
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ValueError(f"the webhook secret_file {path} cannot be read: {exc.strerror}") from None
    if len(data) > MAX_SECRET_BYTES:
        raise ValueError(f"the webhook secret_file is larger than {MAX_SECRET_BYTES} bytes")
    try:
        text = data.decode("utf-8").strip()
    except UnicodeDecodeError:
        raise ValueError("the webhook secret_file is not UTF-8 text") from None
    if len(text) < MIN_SECRET_LENGTH:
        raise ValueError(f"the webhook secret_file holds fewer than {MIN_SECRET_LENGTH} characters")
    return text


def named(targets: list[WebhookTarget]) -> list[WebhookTarget]:
    """Each target with a name (webhook-<n> by position when unnamed); names unique."""
    result = [
        t if t.name is not None else t.model_copy(update={"name": f"webhook-{i}"})
        for i, t in enumerate(targets, start=1)
    ]
    names = [t.name for t in result]
    for name in names:
        if names.count(name) > 1:
            raise ValueError(f"two webhooks are named {name!r}: names must differ")
    return result
