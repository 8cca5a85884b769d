"""The `HttpSettings` section of the settings. HTTPS, off unless both files are set
(docs/security.md, "TLS"), and the limits on slow and numerous connections
(docs/security.md, "Guessing and slow clients").
"""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar, Self

from pydantic import Field, model_validator

from server.settings.section import Section


class HttpSettings(Section):
    """HTTPS, off unless both files are set (docs/security.md, "TLS"), and the limits on
    slow and numerous connections (docs/security.md, "Guessing and slow clients").
    """

    title: ClassVar[str] = "HTTP server"

    tls_cert_file: Path | None = Field(
        None,
        description="the server's certificate (PEM, its chain after it): with tls_key_file, "
        "the HTTP port serves https and wss only (TLS 1.2 or later)",
    )
    tls_key_file: Path | None = Field(
        None,
        description="the private key (PEM, not encrypted) of tls_cert_file; readable by the "
        "server's user only",
    )
    http_header_timeout: float = Field(
        10.0,
        ge=0.5,
        le=300,
        description="seconds a connection has to send a request's headers (from its first "
        "byte, or from connecting); then it is closed",
    )
    http_keepalive_timeout: float = Field(
        5.0, ge=0.5, le=3600, description="seconds an idle keep-alive connection stays open"
    )
    http_max_connections: int = Field(
        512,
        ge=16,
        le=100_000,
        description="open HTTP and WebSocket connections in all; at the limit the oldest one "
        "still waiting for its headers is closed for a new one",
    )
    http_max_connections_per_address: int = Field(
        64,
        ge=1,
        le=100_000,
        description="open HTTP connections from one address (not a trusted proxy), used up "
        "to http_max_connections",
    )

    @model_validator(mode="after")
    def _tls_pair(self) -> Self:
        """A certificate without its key (or the reverse) cannot serve https, and serving
        plain http instead would send the tokens in clear that the setting was meant to
        protect: refused at load. The files themselves are read at start
        (server/bootstrap/tls.py)."""
        if (self.tls_cert_file is None) != (self.tls_key_file is None):
            missing = "tls_key_file" if self.tls_key_file is None else "tls_cert_file"
            raise ValueError(f"tls_cert_file and tls_key_file go together: {missing} is not set")
        return self
