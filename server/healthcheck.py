"""`python -m server.healthcheck URL`: exit 0 when the service at URL answers, 1 when not.

The containers' health checks (docker-compose.yml, Dockerfile): the image has
no curl, and a check should depend on nothing but the Python it already runs.
`http://HOST:PORT/PATH` must answer 200 (the server's GET /health is open to
anyone: server/security/policy.py); `tcp://HOST:PORT` must accept a connection
(a simulator: nothing is sent, so the robot simulator sees a client come and go).
Standard library only, so it starts in a fraction of the server's import time.
"""

from __future__ import annotations

import socket
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
    if parts.scheme == "http" and parts.hostname:
        try:
            with urllib.request.urlopen(url, timeout=TIMEOUT) as answer:
                return None if answer.status == 200 else f"{url}: HTTP {answer.status}"
        except (urllib.error.URLError, OSError) as exc:
            return f"{url}: {exc}"
    return f"{url}: give http://HOST:PORT/PATH or tcp://HOST:PORT"


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m server.healthcheck http://HOST:PORT/PATH | tcp://HOST:PORT")
        return 2
    problem = check(args[0])
    if problem:
        print(f"unhealthy: {problem}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
