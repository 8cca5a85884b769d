"""Who holds the /ws slots, and the end of a revoked token's live views.

A live view is one open /ws connection, held by the token that opened it
(with a ticket or its bearer secret). `LiveViews` decides whether one more
may open and closes a token's views when it is revoked:

- at most `max_broadcast_clients` in all;
- at most `max_broadcast_clients_per_token` per token, so one leaked or
  runaway token cannot take every slot;
- the last `broadcast_clients_reserved` slots (at most all but one) only for
  maintenance and admin, so whoever must recover the cell can watch it while
  viewers and operators hold everything else;
- `revoke(token_id)` ends every view of that token at once (close 4401), and
  any view of it that opens later: a ticket redeemed or a handshake under way
  when the token was revoked still ends.

Each view waits on a plain future, not a task of its own, so revocation
costs the fan-out nothing.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field

from server.security.tokens import Principal, Role

CLOSE_UNAUTHORIZED = 4401
REVOKED_REASON = "unauthorized: the token was revoked"
PRIVILEGED = Role.MAINTENANCE  # this role and above may use the reserved slots


@dataclass(eq=False, slots=True)
class LiveView:
    """One open /ws connection; `ended` is set with (close code, reason) to end it."""

    principal: Principal
    ended: asyncio.Future[tuple[int | None, str]] = field(
        default_factory=lambda: asyncio.get_running_loop().create_future()
    )

    def end(self, code: int, reason: str) -> None:
        if not self.ended.done():
            self.ended.set_result((code, reason))


class LiveViews:
    """The open live views by token, and the limits on opening one more."""

    def __init__(self, max_clients: int, per_token: int = 10, reserved: int = 0) -> None:
        self.max_clients = max_clients
        self.per_token = per_token
        self.reserved = reserved
        self._by_token: dict[str, set[LiveView]] = {}
        self._count = 0
        self._unprivileged = 0
        self._revoked: set[str] = set()

    @property
    def count(self) -> int:
        return self._count

    def refusal(self, principal: Principal) -> str | None:
        """Why `principal` may not open one more view now (None: it may)."""
        if self._count >= self.max_clients:
            return f"too many clients (max {self.max_clients})"
        held = len(self._by_token.get(principal.token_id, ()))
        if held >= self.per_token:
            return (
                f"token {principal.token_id} already has {held} live views "
                "(max_broadcast_clients_per_token)"
            )
        reserved = min(self.reserved, self.max_clients - 1)
        if principal.role < PRIVILEGED and self._unprivileged >= self.max_clients - reserved:
            return (
                f"too many clients: the last {reserved} of {self.max_clients} are kept "
                "for maintenance and admin"
            )
        return None

    def open(self, principal: Principal) -> LiveView:
        """Count a new view (after `refusal` said None); ended at once if its token is revoked."""
        view = LiveView(principal)
        self._by_token.setdefault(principal.token_id, set()).add(view)
        self._count += 1
        self._unprivileged += principal.role < PRIVILEGED
        if principal.token_id in self._revoked:
            view.end(CLOSE_UNAUTHORIZED, REVOKED_REASON)
        return view

    def close(self, view: LiveView) -> None:
        views = self._by_token.get(view.principal.token_id)
        if views is None or view not in views:
            return
        views.discard(view)
        if not views:
            del self._by_token[view.principal.token_id]
        self._count -= 1
        self._unprivileged -= view.principal.role < PRIVILEGED

    def revoke(self, token_id: str) -> int:
        """End every view of the token now and any it opens later; how many were open."""
        self._revoked.add(token_id)
        views = self._by_token.get(token_id, set())
        for view in views:
            view.end(CLOSE_UNAUTHORIZED, REVOKED_REASON)
        return len(views)
