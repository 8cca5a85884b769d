"""The audit trail: every command, every admin action and every refused attempt.

Each row says who (the principal the gate left in the request's state, else
"anonymous"), from where, what (method and path), the outcome and the reason.
The rows are served by `GET /audit` (server/api/admin.py).

An action is on record before it is answered, so a crash at the answer cannot
leave a change nobody is named for:

- a command's row goes into the commit of its event (`note`: the worker's
  recorder writes it with the event and everything the event caused, and the
  answer waits for that commit);
- a change to a file or a setting (tokens, settings, the workpiece library) is
  recorded first, durably, as its gate (`record_before_change`): if the
  journal cannot write, the change is refused (503) and nothing is touched;
  then the file is written (`save`), and if that fails (a full disk) the
  answer is 507, memory is left as it was, and the failure gets its own row.

What is left, the refusals (401/403/429 from the gate, 422 and the like) and
the few requests that change nothing kept (a WebSocket ticket), is written by
an observer of server/api/observe.py once the answer has gone, without waiting
for the disk; identical refusals within `audit_repeat_window` are one row with
a count (server/api/audit_repeats.py). Reads are not audited, unless they were
refused.
"""

from __future__ import annotations

import asyncio
import errno
import logging
import time
from collections.abc import Callable
from typing import Any, TypeVar

from fastapi import Request
from starlette.types import Scope

from server.api.audit_repeats import AuditRepeats
from server.api.observe import Observer
from server.api.schemas import ErrorView, QueueFullResult
from server.common.errors import ChangeNotSaved, JournalUnavailable
from server.core.machine.events import AuditNote, Outcome
from server.security.tokens import Principal
from server.storage.journal import Journal, Record, records

log = logging.getLogger(__name__)
T = TypeVar("T")

# What `record_before_change` and `save` may answer, for the routes' documentation.
STORAGE_REFUSALS: dict[int | str, dict[str, Any]] = {
    503: {
        "model": QueueFullResult,
        "description": "the journal cannot write (a full disk): nothing was changed",
    },
    507: {
        "model": ErrorView,
        "description": "the change could not be saved (no room on the disk): nothing was "
        "changed; the failure is in the audit trail",
    },
}

# A write that failed for want of room: 507 Insufficient Storage (any other failure: 503).
NO_ROOM = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG})


def _who(scope: Scope) -> tuple[str, str, str]:
    """The principal, the client's address and the action (method and path) of a request."""
    state = scope.get("state") or {}  # request.state, as the gate and the routes left it
    principal: Principal | None = state.get("principal")
    address = state.get("client_address")  # the gate's: the peer, or a trusted proxy's word
    if address is None:
        client = scope.get("client")
        address = client[0] if client else "unknown"
    return (
        principal.describe() if principal else "anonymous",
        address,
        f"{scope['method']} {scope['path']}",
    )


def source_of(scope: Scope) -> str:
    """Who sent a command over the API, as its event's `source` says it: `api:<token name>`.

    The token's name is what a person at the panel knows the sender by ("line 3 HMI"),
    so a stop reason built from it says who stopped the cell. The address stays in the
    audit row (server/api/audit.py), not here. Without a principal (a server with no
    gate, in tests): `api:<host>`.
    """
    principal = scope.get("state", {}).get("principal")
    if principal is not None:
        return f"api:{principal.name}"
    client = scope.get("client")
    return f"api:{client[0] if client else 'unknown'}"


def row(scope: Scope, outcome: str, detail: str) -> Record:
    """The audit row of a request."""
    principal, address, action = _who(scope)
    return records.audit(time.time(), principal, address, action, outcome, detail)


def _journal(request: Request) -> Journal:
    journal: Journal | None = request.app.state.cell.journal
    assert journal is not None, "the cell is not started"
    return journal


def note(scope: Scope, label: Callable[[Outcome], str]) -> AuditNote:
    """Who sends this command, for the row committed with its event."""
    principal, address, action = _who(scope)
    return AuditNote(principal, address, action, label)


def answered(scope: Scope, outcome: Outcome) -> None:
    """Tell the observer how a command's answer stands on record.

    Its row was committed with the event (`note`), so the observer leaves it; or, when
    the event is not on record, the observer tries once more, with why.
    """
    state = scope.setdefault("state", {})
    if outcome.journal_problem is None:
        state["audited"] = True
    else:
        state["audit_reason"] = f"event {outcome.event_id}: {outcome.message}"


async def record_before_change(request: Request, detail: str) -> None:
    """Put the change on record, durably, before it is made; JournalUnavailable if not possible.

    The observer then leaves the request alone: its row is written.
    """
    written = _journal(request).append([row(request.scope, "accepted", detail)])
    if written is not None:
        try:
            await written
        except Exception as exc:
            raise JournalUnavailable(str(exc)) from exc
    request.state.audited = True


async def save(request: Request, what: str, write: Callable[[], T]) -> T:
    """Write a change already on record (off the loop); ChangeNotSaved if the disk refuses it.

    `write` must leave memory as it was when it fails (write the file first). The
    failure gets its own audit row beside the one that recorded the change.
    """
    try:
        return await asyncio.to_thread(write)
    except OSError as exc:
        status = 507 if exc.errno in NO_ROOM else 503
        problem = exc.strerror or str(exc)
        log.error("%s could not be saved: %s", what, exc)
        failure = row(request.scope, f"failed ({status})", f"{what}: not saved: {problem}")
        _journal(request).append([failure], durable=False)
        raise ChangeNotSaved(what, problem, status) from exc


# The refusals of a read that are audited: the gate's (no token, too low a role, locked out).
AUDITED_READ_REFUSALS = frozenset({401, 403, 429})


def audit_observer(
    journal_of: Callable[[Scope], Journal | None], repeats: AuditRepeats | None = None
) -> Observer:
    """Record what no route put on record itself: refusals, and changes kept nowhere.

    With `repeats`, identical refusals within its window are one row with a count
    (server/api/audit_repeats.py).
    """

    def observe(scope: Scope, status: int, seconds: float) -> None:
        method = scope["method"]
        if method in ("GET", "HEAD", "OPTIONS") and status not in AUDITED_READ_REFUSALS:
            return
        state = scope.get("state") or {}
        if state.get("audited"):  # committed before the answer, with the action
            return
        journal = journal_of(scope)
        if journal is None:
            return
        outcome = "accepted" if status < 400 else f"refused ({status})"
        detail = state.get("audit_reason", "") or ""
        if repeats is not None and status >= 400:
            repeats.refused((*_who(scope), outcome, detail))
            return
        journal.append([row(scope, outcome, detail)], durable=False)

    return observe
