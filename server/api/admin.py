"""The administration routes: tokens, WebSocket tickets, the audit trail, the settings.

Who may call them is not decided here: the gate (server/api/access.py) has
already checked every request against the policy table
(server/security/policy.py) and left its `principal` in the request's state.
A route that changes something puts it on record first and then makes it
(server/api/audit.py: `record_before_change`, then `save` for a file): a
journal that cannot write refuses the change (503), a file that cannot be
written leaves it unapplied (507).
"""

from __future__ import annotations

import asyncio
import logging
from typing import Annotated, Any, Literal

from fastapi import APIRouter, HTTPException, Query, Request, Response
from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, ConfigDict, ValidationError

from server.api import audit
from server.api.access import access_of
from server.api.analytics import csv_export
from server.api.declared_query import DeclaredQueryRoute
from server.api.runtime_settings import RUNTIME_SETTINGS, SettingsChange, plan_change
from server.api.schemas import ErrorView, text_body
from server.api.time_window import Since, Until, time_window
from server.common.values import Name
from server.security.tokens import Role, last_admin_refusal
from server.settings.model import Settings
from server.settings.runtime import sources_of
from server.storage.journal import Journal

router = APIRouter(tags=["access"], route_class=DeclaredQueryRoute)


class TicketView(BaseModel):
    ticket: str
    expires_in_s: float


class TokenRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")

    name: Name
    role: Literal["viewer", "operator", "maintenance", "admin"]


@router.post("/ws-ticket", response_model=TicketView)
async def issue_ticket(request: Request) -> TicketView:
    """A one-shot ticket for `/ws?ticket=...`, valid a few seconds."""
    try:
        ticket, ttl = access_of(request).tickets.issue(request.state.principal)
    except OverflowError as exc:
        raise HTTPException(503, str(exc)) from exc
    return TicketView(ticket=ticket, expires_in_s=ttl)


@router.get("/tokens")
async def list_tokens(request: Request) -> dict[str, Any]:
    """Every token, without secrets."""
    return {"tokens": access_of(request).tokens.list()}


@router.post("/tokens", status_code=201, responses=audit.STORAGE_REFUSALS)
async def create_token(request: Request, body: TokenRequest) -> dict[str, Any]:
    """A new token; its secret is shown once, in this answer only."""
    tokens = access_of(request).tokens
    entry, token = tokens.mint(body.name, Role.parse(body.role))
    what = f"created token {entry.id} ({body.name}, {body.role})"
    await audit.record_before_change(request, what)
    await audit.save(request, what, lambda: tokens.add(entry))
    return {**entry.public(), "token": token}


@router.delete(
    "/tokens/{token_id}",
    status_code=204,
    response_class=Response,
    responses={
        404: {"model": ErrorView, "description": "no such token"},
        409: {"model": ErrorView, "description": "the last admin token: create another first"},
        **audit.STORAGE_REFUSALS,
    },
)
async def revoke_token(request: Request, token_id: str) -> Response:
    """Revoke a token at once (once saved: a revocation that cannot be saved is refused)."""
    access = access_of(request)
    try:
        entry = access.tokens.get(token_id)
    except KeyError:
        raise HTTPException(404, f"no token {token_id!r}") from None
    async with access.revoking:  # two revocations at once cannot both pass the check below
        if access.tokens.is_last_admin(token_id):  # its audit row says why (app.py)
            raise HTTPException(409, last_admin_refusal(entry))
        what = f"revoked token {entry.id} ({entry.name})"
        await audit.record_before_change(request, what)
        # Saved first, then its tickets void and its live views closed (server/api/access.py).
        await audit.save(request, what, lambda: access.revoke(token_id))
    return Response(status_code=204)


AuditText = Annotated[str | None, Query(max_length=120)]


def _audit_filters(
    principal: str | None, action: str | None, outcome: str | None
) -> dict[str, str]:
    given = {"principal": principal, "action": action, "outcome": outcome}
    return {k: v for k, v in given.items() if v}


@router.get("/audit")
async def get_audit(
    request: Request,
    since: Since = None,
    until: Until = None,
    principal: AuditText = None,
    action: AuditText = None,
    outcome: AuditText = None,
    limit: int = Query(100, ge=1, le=10_000),
    offset: int = Query(0, ge=0, le=10_000_000),
) -> dict[str, Any]:
    """Who did what, when, from where, with what outcome; newest first, filterable."""
    window = time_window(since, until)
    journal: Journal = request.app.state.cell.journal
    request.app.state.audit_repeats.flush()  # the refusals being folded, counted so far
    await journal.caught_up()
    filters = _audit_filters(principal, action, outcome)
    rows, total = await asyncio.gather(
        asyncio.to_thread(
            journal.query,
            "audit",
            since=window.since,
            until=window.until,
            filters=filters,
            limit=limit,
            offset=offset,
        ),
        asyncio.to_thread(
            journal.count, "audit", since=window.since, until=window.until, filters=filters
        ),
    )
    return {"audit": rows, "total": total, "limit": limit, "offset": offset}


@router.get(
    "/audit.csv", response_class=Response, responses={200: {"content": text_body("text/csv")}}
)
async def export_audit(
    request: Request,
    since: Since = None,
    until: Until = None,
    principal: AuditText = None,
    action: AuditText = None,
    outcome: AuditText = None,
) -> Response:
    """The audit trail as CSV, oldest first."""
    window = time_window(since, until)
    request.app.state.audit_repeats.flush()  # the refusals being folded, counted so far
    return await csv_export(
        request.app.state.cell.journal,
        "audit",
        window.since,
        window.until,
        _audit_filters(principal, action, outcome),
    )


@router.get("/settings")
async def get_settings(request: Request) -> dict[str, Any]:
    """The settings in force; the one secret, mqtt_password, is shown as **********.

    Beside the values, `sources` names where each comes from (runtime: changed with
    PATCH /settings and saved in the data directory, standing over the rest; command
    line; environment; file: the config file; default), and `runtime_settings` lists
    the settings PATCH changes at once (any other takes effect only at a restart).
    """
    settings: Settings = request.app.state.settings
    cell = request.app.state.cell
    return {
        **settings.model_dump(mode="json"),
        "sources": sources_of(settings, cell.runtime_settings),
        "runtime_settings": list(RUNTIME_SETTINGS),
    }


@router.patch("/settings", responses={**audit.STORAGE_REFUSALS})
async def patch_settings(request: Request, body: SettingsChange) -> dict[str, Any]:
    """Change settings that apply at once, and keep them over a restart; audited with
    old and new values.

    Each keeps its type and bounds from the settings model (GET /settings shows the
    values in force and where each comes from); a setting that takes effect only at a
    restart is refused, saying where to set it. The change is on record, then saved in
    the data directory (runtime-settings.json, written atomically, 0600), then applied:
    a disk that refuses it leaves it unapplied (507 or 503).
    """
    settings: Settings = request.app.state.settings
    cell = request.app.state.cell
    try:
        changes = plan_change(settings, body)
    except ValidationError as exc:  # a rule across settings
        raise RequestValidationError(
            [{**error, "loc": ("body", *error["loc"])} for error in exc.errors()]
        ) from None
    detail = "; ".join(f"{k}: {old!r} -> {new!r}" for k, (old, new) in changes.items())
    await audit.record_before_change(request, detail)
    kept = {name: getattr(settings, name) for name in cell.runtime_settings}
    kept.update({name: new for name, (_, new) in changes.items()})
    store = cell.stores.runtime_settings
    await audit.save(request, detail, lambda: store.save(kept))
    for name, (_, new) in changes.items():
        setattr(settings, name, new)
    cell.runtime_settings |= set(changes)
    if "logging_level" in changes:
        logging.getLogger().setLevel(settings.logging_level)
    return {"changed": {k: {"old": old, "new": new} for k, (old, new) in changes.items()}}
