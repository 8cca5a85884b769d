"""Slow and idle HTTP clients are closed, and open connections are bounded.

Why: uvicorn waits for a request's headers as long as the client likes, and
accepts every connection it is offered. A client sending one header line every
few seconds holds its connection (and a file descriptor) for good; a thousand
of them held a thousand, and the next one, the e-stop's perhaps, had to wait
for the process's descriptors. uvicorn has no header timeout of its own, so
this is one: its HTTP protocol (httptools, what uvicorn picks by default),
subclassed, handed to uvicorn as its `http` option by `uvicorn_options`
(server/__main__.py), which `python -m server`, the tests and the benchmarks
all serve with.

- A request's headers must be complete within `http_header_timeout` seconds:
  counted from the connection for its first request, from the first byte of
  each later one (between requests the keep-alive timeout, uvicorn's
  `timeout_keep_alive` = `http_keepalive_timeout`, closes an idle connection).
  A late one is closed, with a 408 if it had sent part of a request.
- At most `http_max_connections` connections are open (HTTP and WebSocket),
  and at most `http_max_connections_per_address` HTTP connections from one
  client address (a trusted proxy's excepted: it carries many clients). A new
  connection over either bound is not refused while another is only waiting:
  the oldest connection still waiting for its headers is closed for it (one
  that never sent a whole request before one that has, between requests). So
  slow clients make room for each other and for whoever sends a request
  promptly, the e-stop included; only when every connection is busy with a
  request is the new one answered 503 (Retry-After) and closed.
"""

from __future__ import annotations

import asyncio
import ipaddress
import json
import logging
import time
from collections import Counter
from dataclasses import dataclass
from typing import Any, cast

from starlette.types import Scope
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from server.api.door import on_headers
from server.security.forwarded import parse_networks
from server.settings.model import Settings

log = logging.getLogger(__name__)

NOTICE_EVERY_S = 60.0  # a limit reached is logged at most this often


def _answer(status: str, detail: str, *headers: str) -> bytes:
    """A whole HTTP/1.1 answer that closes the connection, written to the socket as it is."""
    body = json.dumps({"detail": detail}).encode()
    head = [f"HTTP/1.1 {status}", "content-type: application/json", *headers]
    head += ["connection: close", f"content-length: {len(body)}", "", ""]
    return "\r\n".join(head).encode() + body


REQUEST_TIMEOUT = _answer(
    "408 Request Timeout", "the request's headers did not arrive in time (http_header_timeout)"
)
BUSY = _answer("503 Service Unavailable", "too many connections busy: try again", "retry-after: 1")


@dataclass(frozen=True, slots=True)
class ConnectionLimits:
    """The settings this module applies."""

    header_timeout: float
    max_connections: int
    max_per_address: int
    trusted_proxies: tuple[ipaddress.IPv4Network | ipaddress.IPv6Network, ...] = ()

    @classmethod
    def of(cls, settings: Settings) -> ConnectionLimits:
        return cls(
            settings.http_header_timeout,
            settings.http_max_connections,
            min(settings.http_max_connections_per_address, settings.http_max_connections),
            tuple(parse_networks(settings.trusted_proxies)),
        )


class _Registry:
    """One server's connections waiting for headers, oldest first, and the count per address."""

    def __init__(self, limits: ConnectionLimits) -> None:
        self.limits = limits
        self.per_address: Counter[str] = Counter()
        # Waiting for a request's headers: `fresh` never sent a whole one, `between` has.
        self.fresh: dict[GuardedHttpProtocol, None] = {}
        self.between: dict[GuardedHttpProtocol, None] = {}
        self.closing = 0  # closed by this module, not yet gone from uvicorn's connections
        self._noticed = -NOTICE_EVERY_S

    def exempt(self, address: str) -> bool:
        """Whether `address` is a trusted proxy's (no per-address share)."""
        if not self.limits.trusted_proxies:
            return False
        try:
            parsed = ipaddress.ip_address(address)
        except ValueError:
            return False
        return any(parsed in network for network in self.limits.trusted_proxies)

    def oldest_waiting(self, address: str | None = None) -> GuardedHttpProtocol | None:
        """The connection to close for a new one: from `address` if given, fresh first."""
        for waiting in (self.fresh, self.between):
            for connection in waiting:
                if address is None or connection.address == address:
                    return connection
        return None

    def notice(self, what: str) -> None:
        now = time.monotonic()
        if now - self._noticed >= NOTICE_EVERY_S:
            self._noticed = now
            log.warning("%s (logged at most once a minute)", what)


class GuardedHttpProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol with a header deadline and the connection bounds.

    `guarded_http_protocol` makes a subclass per server, holding its registry.
    """

    registry: _Registry

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.address = "unknown"
        self.counted = False  # in registry.per_address
        self.closed_here = False  # counted in registry.closing
        self.partial = False  # part of a request arrived, its headers not all yet
        self.header_deadline: asyncio.TimerHandle | None = None

    # --- the connection's life ------------------------------------------------

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        registry = self.registry
        self.address = self.client[0] if self.client else "unknown"
        if not registry.exempt(self.address):
            if registry.per_address[self.address] >= registry.limits.max_per_address:
                victim = registry.oldest_waiting(self.address)
                if victim is None:
                    registry.notice(
                        f"{self.address} holds http_max_connections_per_address "
                        f"({registry.limits.max_per_address}) busy connections: refusing more"
                    )
                    self._close(BUSY)
                    return
                victim._close(REQUEST_TIMEOUT if victim.partial else None)
            self.counted = True
            registry.per_address[self.address] += 1
        if len(self.connections) - registry.closing > registry.limits.max_connections:
            victim = registry.oldest_waiting()
            registry.notice(
                f"http_max_connections ({registry.limits.max_connections}) open: closing the "
                "oldest connections still waiting for their headers"
            )
            if victim is None:
                self._close(BUSY)
                return
            victim._close(REQUEST_TIMEOUT if victim.partial else None)
        registry.fresh[self] = None
        self._arm_deadline()

    def connection_lost(self, exc: Exception | None) -> None:
        self._forget()
        if self.closed_here:
            self.closed_here = False
            self.registry.closing -= 1
        super().connection_lost(exc)

    def handle_websocket_upgrade(self) -> None:
        """A WebSocket is no HTTP connection waiting: bounded by the live-view limits."""
        self._forget()
        super().handle_websocket_upgrade()

    # --- a request's progress ---------------------------------------------------

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self.partial = True
        if self.header_deadline is None:  # a later request on a kept-alive connection
            self._arm_deadline()

    def on_headers_complete(self) -> None:
        self._disarm_deadline()
        self.partial = False
        self.registry.fresh.pop(self, None)
        self.registry.between.pop(self, None)
        ready = getattr(self.loop, "_ready", None)  # asyncio's line of callbacks to run
        queued = len(ready) if ready is not None else -1
        super().on_headers_complete()
        scope = cast("Scope", self.scope)  # uvicorn's TypedDict, the ASGI scope the door reads
        if on_headers(self.app, scope) and ready is not None:
            _first_in_line(ready, queued, self.tasks)

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if self.timeout_keep_alive_task is not None:  # idle now, kept alive for the next one
            self.registry.between[self] = None

    # --- helpers ----------------------------------------------------------------

    def _arm_deadline(self) -> None:
        self.header_deadline = self.loop.call_later(
            self.registry.limits.header_timeout, self._headers_late
        )

    def _disarm_deadline(self) -> None:
        if self.header_deadline is not None:
            self.header_deadline.cancel()
            self.header_deadline = None

    def _headers_late(self) -> None:
        self.header_deadline = None
        self._close(REQUEST_TIMEOUT if self.partial else None)

    def _close(self, answer: bytes | None) -> None:
        """Close the connection (after `answer`, if any); it is forgotten at once."""
        self._forget()
        if self.transport.is_closing():
            return
        if answer is not None:
            self.transport.write(answer)
        self.closed_here = True
        self.registry.closing += 1
        self.transport.close()

    def _forget(self) -> None:
        """Out of the registry (idempotent): closed, lost, or become a WebSocket."""
        self._disarm_deadline()
        registry = self.registry
        registry.fresh.pop(self, None)
        registry.between.pop(self, None)
        if self.counted:
            self.counted = False
            registry.per_address[self.address] -= 1
            if registry.per_address[self.address] <= 0:
                del registry.per_address[self.address]


def _first_in_line(ready: Any, queued: int, tasks: set[asyncio.Task[None]]) -> None:
    """Move the step uvicorn just queued for a stop's task to the front of the loop's
    line, so it runs as soon as the callback reading its bytes returns: what it waits
    for is then the stop lane's own work, never the steps of a flood's requests queued
    before it (server/api/door.py: `on_headers`). Only that one step, and only when it
    is certainly the task's (a pipelined request starts no task here)."""
    if len(ready) != queued + 1:
        return
    step = ready[-1]
    if getattr(getattr(step, "_callback", None), "__self__", None) in tasks:
        ready.pop()
        ready.appendleft(step)


def guarded_http_protocol(limits: ConnectionLimits) -> type[asyncio.Protocol]:
    """The protocol class for one server (its own registry): uvicorn's `http` option."""
    return type("GuardedHttpProtocol", (GuardedHttpProtocol,), {"registry": _Registry(limits)})
