"""Who may do what, checked in one place: the HTTP gate and the WebSocket's handshake.

Every HTTP request is checked by `Access.check`, which the HTTP door
(server/api/door.py) asks first (the policy table in server/security/policy.py
says which role it needs); the WebSocket checks its ticket or bearer token in
server/api/ws.py with `authenticate_websocket`. Both
read the token with the same parser (`bearer_token`), so the two doors cannot
drift apart. The refusals they leave in the request's state are written to the
audit trail by server/api/audit.py; server/api/openapi_doc.py describes the
same gate in openapi.json, from the same table.
"""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import time
from collections.abc import Callable
from pathlib import Path

from fastapi import WebSocket
from starlette.requests import HTTPConnection
from starlette.types import Scope

from server.security.forwarded import (
    UNKNOWN,
    client_address,
    parse_networks,
    rewritten_by_server,
)
from server.security.policy import WEBSOCKET_ROLE, role_for_request
from server.security.throttle import AuthThrottle
from server.security.tickets import TicketBook
from server.security.tokens import Principal, TokenEntry, TokenStore
from server.settings.access import AccessSettings

log = logging.getLogger(__name__)
CHALLENGE = {"WWW-Authenticate": "Bearer"}  # on every 401
LOCKED_OUT = "locked_out"  # in a WebSocket's scope state: (seconds to wait, why)
CLOSE_LOCKED_OUT = 4429  # a WebSocket from a locked-out address: 429's close code
# A refusal: status, reason, headers to add.
Refusal = tuple[int, str, dict[str, str] | None]
REWRITTEN = (
    "the server in front of the app replaced this request's address with one from its "
    "X-Forwarded-For, which cannot be checked; serve the app with proxy headers off "
    "(python -m server does; uvicorn: --no-proxy-headers) and name the proxies in "
    "trusted_proxies"
)


class Access:
    """The app's token store, tickets, network allowlist and trusted proxies."""

    def __init__(self, settings: AccessSettings, data_path: Path) -> None:
        self.settings = settings
        self.tokens = TokenStore(data_path)
        self.tickets = TicketBook()
        self.networks = parse_networks(settings.trusted_networks)
        self.proxies = parse_networks(settings.trusted_proxies)
        self._rewrite_logged = False
        # Told of every revocation (the WebSocket hub closes the token's live views).
        self.revocation_listeners: list[Callable[[str], object]] = []
        self.revoking = asyncio.Lock()  # one revocation at a time (the last admin stays)
        # Bad tokens and tickets per client address (server/security/throttle.py).
        self.throttle = AuthThrottle(
            settings.auth_failure_limit, settings.auth_failure_window, settings.auth_lockout_s
        )

    def locked_out(self, host: str) -> tuple[int, str] | None:
        """Seconds `host` must wait after too many bad tokens, and why; None if it need not."""
        wait = self.throttle.retry_after(host, time.monotonic())
        if wait is None:
            return None
        # The same words for every refusal of one lockout: its audit rows fold into one.
        return wait, (
            f"too many bad tokens from {host}: try again after Retry-After "
            f"(auth_failure_limit {self.settings.auth_failure_limit} within "
            f"{self.settings.auth_failure_window:g} s)"
        )

    def bad_credential(self, host: str) -> None:
        """Count a bad token or ticket from `host`; the lockout it may start is logged once."""
        if self.throttle.failed(host, time.monotonic()):
            log.warning(
                "%s sent %d bad tokens or tickets within %g s: answered 429 for %g s "
                "(the e-stop excepted)",
                host,
                self.settings.auth_failure_limit,
                self.settings.auth_failure_window,
                self.settings.auth_lockout_s,
            )

    def verify_token(self, host: str, token: str) -> Principal | None:
        """The token's principal; a bad one counts against `host`."""
        principal = self.tokens.verify(token)
        if principal is None:
            self.bad_credential(host)
        return principal

    def revoke(self, token_id: str) -> TokenEntry:
        """Revoke a token everywhere at once; KeyError for an unknown id.

        Its next request is refused (the store), its unused tickets are void,
        and every listener hears of it: its open /ws views are closed.
        """
        entry = self.tokens.revoke(token_id)
        self.tickets.forget(token_id)
        for listener in self.revocation_listeners:
            listener(token_id)
        return entry

    def check(self, scope: Scope, *, stop: bool) -> Refusal | None:
        """The gate of an HTTP request: None if it may pass, else its status, reason and the
        headers to add (a 401 asks for a bearer token, a 429 says when to try again).

        It runs before routing and matches the request's own path against the policy
        table (`role_for_request`): a path no entry matches needs ADMIN, so a new route
        stays closed until the table names it. Why not a FastAPI dependency: resolving
        one per request costs a fifth of a GET /state (docs/benchmarks.md), and a
        refused request should cost no routing at all. A `stop` is never locked out by
        the bad-token throttle (server/security/throttle.py).

        It leaves the client's address and `principal` in the request's state for the
        routes and the audit trail.
        """
        host, refusal = self.screen(scope)
        scope.setdefault("state", {})["client_address"] = host
        if refusal is not None:
            return 403, refusal, None
        needed = role_for_request(scope["method"], scope["path"])
        if needed is None:
            return None
        locked = None if stop else self.locked_out(host)
        if locked is not None:
            wait, why = locked
            return 429, why, {"Retry-After": str(wait)}
        token = bearer_token(scope)
        if token is None:
            return 401, "authentication required: send Authorization: Bearer <token>", CHALLENGE
        principal = self.verify_token(host, token)
        if principal is None:
            return 401, "the token is unknown or revoked", CHALLENGE
        scope.setdefault("state", {})["principal"] = principal
        if principal.role < needed:
            return (
                403,
                f"this needs the {needed.label} role; {principal.name} has {principal.role.label}",
                None,
            )
        return None

    def address_allowed(self, host: str | None) -> bool:
        if not self.networks:
            return True
        try:
            address = ipaddress.ip_address(host or "")
        except ValueError:
            return False
        return any(address in network for network in self.networks)

    def screen(self, scope: Scope) -> tuple[str, str | None]:
        """The client's address (what the audit records) and why it is refused, if it is.

        The address is the peer's, or what a trusted proxy forwarded
        (server/security/forwarded.py); a request whose address the server in
        front already rewrote from X-Forwarded-For is refused, never believed.
        """
        if rewritten_by_server(scope):
            if not self._rewrite_logged:
                self._rewrite_logged = True
                log.error("refusing requests: %s", REWRITTEN)
            return UNKNOWN, REWRITTEN
        host = client_address(scope, self.proxies, self.settings.forwarded_header)
        if not self.address_allowed(host):
            return host or UNKNOWN, f"requests from {host} are not allowed (trusted_networks)"
        return host or UNKNOWN, None


def access_of(connection: HTTPConnection) -> Access:
    """The app's `Access` (`app.state.access`), from a request or a WebSocket."""
    return connection.app.state.access


def bearer_token(scope: Scope) -> str | None:
    """The bearer token of an HTTP or WebSocket Authorization header, from the raw scope."""
    for name, value in scope.get("headers") or ():
        if name == b"authorization":
            scheme, _, token = value.decode("latin-1").partition(" ")
            token = token.strip()
            return token if scheme.lower() == "bearer" and token else None
    return None


def websocket_principal(websocket: WebSocket) -> Principal | None:
    """A WebSocket's principal from its one-shot ticket or bearer token, whatever its role
    (the caller checks the role it needs); None from a refused network or without either.

    From an address locked out after too many bad tokens it is None too, and
    `websocket_lockout` says so (the close code 4429 and the reason); a bad ticket
    or token counts against the address as on HTTP.
    """
    access = access_of(websocket)
    host, refusal = access.screen(websocket.scope)
    if refusal is not None:
        return None
    locked = access.locked_out(host)
    if locked is not None:
        websocket.scope.setdefault("state", {})[LOCKED_OUT] = locked
        return None
    ticket = websocket.query_params.get("ticket")
    token = bearer_token(websocket.scope)
    if ticket:
        principal = access.tickets.redeem(ticket)
        if principal is None:
            access.bad_credential(host)
        return principal
    return access.verify_token(host, token) if token else None


def websocket_lockout(websocket: WebSocket) -> tuple[int, str] | None:
    """The close code and reason of a WebSocket refused for its address's lockout, if it was."""
    locked: tuple[int, str] | None = websocket.scope.get("state", {}).get(LOCKED_OUT)
    if locked is None:
        return None
    wait, _ = locked
    return CLOSE_LOCKED_OUT, f"too many bad tokens from this address: try again in {wait} s"


def authenticate_websocket(websocket: WebSocket) -> Principal | None:
    """A /ws principal from its one-shot ticket or bearer token, if allowed."""
    principal = websocket_principal(websocket)
    if principal is None or principal.role < WEBSOCKET_ROLE:
        return None
    return principal
