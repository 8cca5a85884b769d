"""`python -m server.cli.healthcheck URL`: exit 0 when the service at URL answers, 1 when not.

The containers' health checks (docker-compose.yml, Dockerfile): the image has
no curl, and a check should depend on nothing but the Python it already runs.
`http://HOST:PORT/PATH` must answer 200 (the server's GET /health is open to
anyone: server/security/policy.py); `https://...` the same from a server serving
TLS (tls_cert_file); `tcp://HOST:PORT` must accept a connection (a simulator:
nothing is sent, so the robot simulator sees a client come and go).

Over https the certificate is not checked: the check asks the container's own
loopback, where the plant's certificate (issued for the cell's name on the plant
network, not for 127.0.0.1) cannot match, and it sends no token, so there is
nothing to protect; what it must learn is whether the server answers.
Standard library only, so it starts in a fraction of the server's import time.
"""

from __future__ import annotations

import socket
import ssl
import sys
import urllib.error
import urllib.request
from urllib.parse import urlsplit

TIMEOUT = 5.0  # seconds; the container's own `timeout` bounds the whole check


def check(url: str) -> str | None:
    """None when the service answers; otherwise why not, in one line."""
    parts = urlsplit(url)
    if parts.scheme == "tcp" and parts.hostname and parts.port:
        try:
            with socket.create_connection((parts.hostname, parts.port), timeout=TIMEOUT):
                return None
        except OSError as exc:
            return f"{url}: {exc}"
    if parts.scheme in ("http", "https") and parts.hostname:
        unchecked = ssl.create_default_context()
        unchecked.check_hostname = False
        unchecked.verify_mode = ssl.CERT_NONE
        context = unchecked if parts.scheme == "https" else None
        try:
            with urllib.request.urlopen(url, timeout=TIMEOUT, context=context) as answer:
                return None if answer.status == 200 else f"{url}: HTTP {answer.status}"
        except (urllib.error.URLError, OSError) as exc:
            return f"{url}: {exc}"
    return f"{url}: give http(s)://HOST:PORT/PATH or tcp://HOST:PORT"


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m server.cli.healthcheck http(s)://HOST:PORT/PATH | tcp://HOST:PORT")
        return 2
    problem = check(args[0])
    if problem:
        print(f"unhealthy: {problem}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
