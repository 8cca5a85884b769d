"""One-shot WebSocket tickets.

A browser cannot put a bearer token on a WebSocket handshake, and a token in
a URL ends up in proxy logs. So an authenticated client asks for a ticket
(POST /ws-ticket), valid TICKET_TTL_S seconds and usable once, and opens
`/ws?ticket=...`. A leaked ticket is worthless a few seconds later.
"""

from __future__ import annotations

import secrets
import time

from server.security.tokens import Principal

TICKET_TTL_S = 10.0
MAX_OUTSTANDING = 10_000


class TicketBook:
    """Issued tickets, each redeemable once before it expires."""

    def __init__(self, ttl: float = TICKET_TTL_S) -> None:
        self.ttl = ttl
        self._tickets: dict[str, tuple[Principal, float]] = {}

    def issue(self, principal: Principal) -> tuple[str, float]:
        self._expire()
        if len(self._tickets) >= MAX_OUTSTANDING:
            raise OverflowError("too many outstanding tickets; retry shortly")
        ticket = secrets.token_urlsafe(24)
        expires = time.monotonic() + self.ttl
        self._tickets[ticket] = (principal, expires)
        return ticket, self.ttl

    def redeem(self, ticket: str) -> Principal | None:
        """The ticket's principal if valid; the ticket is spent either way."""
        entry = self._tickets.pop(ticket, None)
        if entry is None or entry[1] < time.monotonic():
            return None
        return entry[0]

    def forget(self, token_id: str) -> None:
        """Void the unused tickets of a token (it was revoked)."""
        for ticket in [t for t, (p, _) in self._tickets.items() if p.token_id == token_id]:
            del self._tickets[ticket]

    def _expire(self) -> None:
        now = time.monotonic()
        for ticket in [t for t, (_, expires) in self._tickets.items() if expires < now]:
            del self._tickets[ticket]
