"""The audit trail: every command, every admin action and every refused attempt.

Written to the journal's audit table from the response, by one observer of
server/api/observe.py (no task per request): who (the principal the gate left
in the request's state, else "anonymous"), from where, what, outcome, and the
reason a route or the gate (server/api/access.py) gave. Reads are not audited,
unless they were refused. The rows are served by `GET /audit` (server/api/admin.py).
"""

from __future__ import annotations

import time
from collections.abc import Callable

from starlette.types import Scope

from server.api.observe import Observer
from server.security.tokens import Principal
from server.storage.journal import Journal, records


def audit_observer(journal_of: Callable[[Scope], Journal | None]) -> Observer:
    """Record commands, admin actions and refused attempts in the journal."""

    def observe(scope: Scope, status: int, seconds: float) -> None:
        method = scope["method"]
        if method in ("GET", "HEAD", "OPTIONS") and status not in (401, 403):
            return
        journal = journal_of(scope)
        if journal is None:
            return
        state = scope.get("state") or {}  # request.state, as the routes left it
        principal: Principal | None = state.get("principal")
        who = principal.describe() if principal else "anonymous"
        outcome = "accepted" if status < 400 else f"refused ({status})"
        detail = state.get("audit_reason", "") or ""
        host = state.get("client_address")  # the gate's: the peer, or a trusted proxy's word
        if host is None:
            client = scope.get("client")
            host = client[0] if client else "unknown"
        journal.append(
            [records.audit(time.time(), who, host, f"{method} {scope['path']}", outcome, detail)],
            durable=False,
        )

    return observe
