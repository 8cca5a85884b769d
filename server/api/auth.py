"""Authentication, authorisation and the audit trail, checked in one place.

Every HTTP request goes through `AccessGate` (the policy table in
server/security/policy.py says which role it needs); the WebSocket checks its
ticket or bearer token in server/api/ws.py with `authenticate_websocket`.
Every command, every admin action and every refused attempt is written to the
journal's audit table by `audit_middleware`: who, from where, what, outcome.
`document_access` describes the same gate in openapi.json, from the same table.
"""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import time
from collections.abc import Callable
from typing import Annotated, Any, Literal

from fastapi import APIRouter, HTTPException, Query, Request, Response, WebSocket
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from starlette.requests import HTTPConnection
from starlette.types import ASGIApp, Receive, Scope, Send

from server.api.analytics import csv_export
from server.api.observe import Observer
from server.api.schemas import ErrorView
from server.config import Settings
from server.security.policy import WEBSOCKET_ROLE, required_role, role_for_request
from server.security.tickets import TicketBook
from server.security.tokens import Principal, Role, TokenStore
from server.storage.journal import Journal, records

router = APIRouter(tags=["access"])
RUNTIME_SETTINGS = (
    "error_state_timeout",
    "auto_recovery_enabled",
    "error_recovery_attempts",
    "error_recovery_delay",
    "calibration_max_error_mm",
    "design_cycle_time_s",
    "shift_hours",
    "processing_timeout",
    "logging_level",
)


class Access:
    """The app's token store, tickets and network allowlist."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.tokens = TokenStore(settings.data_path)
        self.tickets = TicketBook()
        self.networks = [ipaddress.ip_network(n, strict=False) for n in settings.trusted_networks]

    def address_allowed(self, host: str | None) -> bool:
        if not self.networks:
            return True
        try:
            address = ipaddress.ip_address(host or "")
        except ValueError:
            return False
        return any(address in network for network in self.networks)


def _access(connection: HTTPConnection) -> Access:
    return connection.app.state.access


def _bearer_in(scope: Scope) -> str | None:
    """The bearer token of an HTTP or WebSocket Authorization header, from the raw scope."""
    for name, value in scope.get("headers") or ():
        if name == b"authorization":
            scheme, _, token = value.decode("latin-1").partition(" ")
            token = token.strip()
            return token if scheme.lower() == "bearer" and token else None
    return None


class AccessGate:
    """ASGI middleware: the one gate of every HTTP request (network, token, role).

    It runs before routing and matches the request's own path against the
    policy table (`role_for_request`): a path no entry matches needs ADMIN, so
    a new route stays closed until the table names it. Why not a FastAPI
    dependency: resolving one per request was a fifth of a GET /state
    (docs/benchmarks.md), and a refused request should cost no routing at all.

    It leaves `principal` (and, when it refuses, `audit_reason`) in the
    request's state for the routes and the audit trail. WebSockets prove who
    they are in server/api/ws.py (`authenticate_websocket`).
    """

    def __init__(self, app: ASGIApp, access: Access) -> None:
        self.app = app
        self.access = access

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        refusal = self._check(scope)
        if refusal is None:
            await self.app(scope, receive, send)
            return
        status, reason = refusal
        scope.setdefault("state", {})["audit_reason"] = reason
        headers = {"WWW-Authenticate": "Bearer"} if status == 401 else None
        await JSONResponse({"detail": reason}, status, headers=headers)(scope, receive, send)

    def _check(self, scope: Scope) -> tuple[int, str] | None:
        """None if the request may pass, else the status and the reason."""
        access = self.access
        client = scope.get("client")
        host = client[0] if client else None
        if not access.address_allowed(host):
            return 403, f"requests from {host} are not allowed (trusted_networks)"
        needed = role_for_request(scope["method"], scope["path"])
        if needed is None:
            return None
        token = _bearer_in(scope)
        if token is None:
            return 401, "authentication required: send Authorization: Bearer <token>"
        principal = access.tokens.verify(token)
        if principal is None:
            return 401, "the token is unknown or revoked"
        scope.setdefault("state", {})["principal"] = principal
        if principal.role < needed:
            return (
                403,
                f"this needs the {needed.label} role; {principal.name} has {principal.role.label}",
            )
        return None


# --- the API description of the gate ----------------------------------------------

BEARER_SCHEME = "bearer"  # the name of the security scheme in openapi.json
_UNTRUSTED = "the client address is not in `trusted_networks`"
_HTTP_METHODS = {"get", "put", "post", "delete", "options", "head", "patch", "trace"}


def _refusal(description: str, **extra: Any) -> dict[str, Any]:
    """A documented 401 or 403: the `{"detail": ...}` body of FastAPI's HTTPException handler."""
    body = {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorView"}}}
    return {"description": description, **extra, "content": body}


def document_access(schema: dict[str, Any]) -> None:
    """Describe `AccessGate` in an OpenAPI document: the bearer scheme, who may call what, 401/403.

    Derived from the policy table, as `AccessGate` is: an operation that needs a role gets the
    security requirement, `x-required-role`, a sentence in its description and the 401 and 403
    it can answer; an open one gets only the 403 of `trusted_networks`, which applies to all.
    """
    components = schema.setdefault("components", {})
    components.setdefault("schemas", {}).setdefault("ErrorView", ErrorView.model_json_schema())
    components["securitySchemes"] = {
        BEARER_SCHEME: {
            "type": "http",
            "scheme": "bearer",
            "bearerFormat": "gc_<id>_<secret>",
            "description": "A token from `POST /tokens` or `<data>/admin.token`, sent as "
            "`Authorization: Bearer <token>`; each operation's `x-required-role` is the "
            "least role it needs (viewer < operator < maintenance < admin).",
        }
    }
    for path, operations in schema.get("paths", {}).items():
        for method, operation in operations.items():
            if method not in _HTTP_METHODS:
                continue
            needed = required_role(method.upper(), path)
            responses = operation.setdefault("responses", {})
            if needed is None:
                responses["403"] = _refusal(_UNTRUSTED)
                continue
            operation["security"] = [{BEARER_SCHEME: []}]
            operation["x-required-role"] = needed.label
            who = {
                Role.VIEWER: "any valid bearer token (every role)",
                Role.ADMIN: "a bearer token with the `admin` role",
            }.get(needed, f"a bearer token with the `{needed.label}` role or higher")
            operation["description"] = (
                f"{operation.get('description', '').rstrip()}\n\nNeeds {who}.".lstrip()
            )
            responses["401"] = _refusal(
                "no bearer token, or the token is unknown or revoked",
                headers={
                    "WWW-Authenticate": {
                        "description": "the scheme to authenticate with",
                        "required": True,
                        "schema": {"type": "string", "enum": ["Bearer"]},
                    }
                },
            )
            responses["403"] = _refusal(
                _UNTRUSTED
                if needed == Role.VIEWER  # no role is below it
                else f"the token's role is below `{needed.label}` (the detail names the role "
                f"needed and the role held), or {_UNTRUSTED}"
            )


def authenticate_websocket(websocket: WebSocket) -> Principal | None:
    """A WebSocket's principal from its one-shot ticket or bearer token, if allowed."""
    access = _access(websocket)
    if not access.address_allowed(websocket.client.host if websocket.client else None):
        return None
    ticket = websocket.query_params.get("ticket")
    token = _bearer_in(websocket.scope)
    principal = (
        access.tickets.redeem(ticket)
        if ticket
        else (access.tokens.verify(token) if token else None)
    )
    if principal is None or principal.role < WEBSOCKET_ROLE:
        return None
    return principal


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
        client = scope.get("client")
        host = client[0] if client else "unknown"
        journal.append(
            [records.audit(time.time(), who, host, f"{method} {scope['path']}", outcome, detail)],
            durable=False,
        )

    return observe


# --- routes ------------------------------------------------------------------


class TicketView(BaseModel):
    ticket: str
    expires_in_s: float


class TokenRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")

    name: str = Field(min_length=1, max_length=100)
    role: Literal["viewer", "operator", "maintenance", "admin"]


@router.post("/ws-ticket", response_model=TicketView)
async def issue_ticket(request: Request) -> TicketView:
    """A one-shot ticket for `/ws?ticket=...`, valid a few seconds."""
    try:
        ticket, ttl = _access(request).tickets.issue(request.state.principal)
    except OverflowError as exc:
        raise HTTPException(503, str(exc)) from exc
    return TicketView(ticket=ticket, expires_in_s=ttl)


@router.get("/tokens")
async def list_tokens(request: Request) -> dict[str, Any]:
    """Every token, without secrets."""
    return {"tokens": _access(request).tokens.list()}


@router.post("/tokens", status_code=201)
async def create_token(request: Request, body: TokenRequest) -> dict[str, Any]:
    """A new token; its secret is shown once, in this answer only."""
    entry, token = _access(request).tokens.create(body.name, Role.parse(body.role))
    request.state.audit_reason = f"created token {entry.id} ({body.name}, {body.role})"
    return {**entry.public(), "token": token}


@router.delete(
    "/tokens/{token_id}",
    status_code=204,
    response_class=Response,
    responses={404: {"model": ErrorView, "description": "no such token"}},
)
async def revoke_token(request: Request, token_id: str) -> Response:
    """Revoke a token at once."""
    try:
        entry = _access(request).tokens.revoke(token_id)
    except KeyError:
        raise HTTPException(404, f"no token {token_id!r}") from None
    request.state.audit_reason = f"revoked token {entry.id} ({entry.name})"
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
    since: float | None = Query(None, ge=0, le=1e11, allow_inf_nan=False),
    until: float | None = Query(None, ge=0, le=1e11, allow_inf_nan=False),
    principal: AuditText = None,
    action: AuditText = None,
    outcome: AuditText = None,
    limit: int = Query(100, ge=1, le=10_000),
    offset: int = Query(0, ge=0, le=10_000_000),
) -> dict[str, Any]:
    """Who did what, when, from where, with what outcome; newest first, filterable."""
    journal: Journal = request.app.state.cell.journal
    await journal.caught_up()
    filters = _audit_filters(principal, action, outcome)
    rows, total = await asyncio.gather(
        asyncio.to_thread(
            journal.query,
            "audit",
            since=since,
            until=until,
            filters=filters,
            limit=limit,
            offset=offset,
        ),
        asyncio.to_thread(journal.count, "audit", since=since, until=until, filters=filters),
    )
    return {"audit": rows, "total": total, "limit": limit, "offset": offset}


@router.get("/audit.csv", response_class=Response, responses={200: {"content": {"text/csv": {}}}})
async def export_audit(
    request: Request,
    since: float | None = Query(None, ge=0, le=1e11, allow_inf_nan=False),
    until: float | None = Query(None, ge=0, le=1e11, allow_inf_nan=False),
    principal: AuditText = None,
    action: AuditText = None,
    outcome: AuditText = None,
) -> Response:
    """The audit trail as CSV, oldest first."""
    return await csv_export(
        request.app.state.cell.journal,
        "audit",
        since,
        until,
        _audit_filters(principal, action, outcome),
    )


@router.get("/settings")
async def get_settings(request: Request) -> dict[str, Any]:
    """The settings in force (nothing secret is kept in settings)."""
    return request.app.state.settings.model_dump(mode="json")


@router.patch("/settings")
async def patch_settings(request: Request, body: dict[str, Any]) -> dict[str, Any]:
    """Change settings that apply at once (RUNTIME_SETTINGS); audited with old and new values."""
    settings: Settings = request.app.state.settings
    unknown = sorted(set(body) - set(RUNTIME_SETTINGS))
    if unknown:
        raise HTTPException(
            422,
            f"not changeable at run time: {', '.join(unknown)}; "
            f"changeable: {', '.join(RUNTIME_SETTINGS)}",
        )
    try:
        merged = Settings.model_validate({**settings.model_dump(), **body})
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise HTTPException(422, f"invalid setting {where}: {first['msg']}") from None
    changes = {
        k: (getattr(settings, k), getattr(merged, k))
        for k in body
        if getattr(settings, k) != getattr(merged, k)
    }
    for key, (_, new) in changes.items():
        setattr(settings, key, new)
    if "logging_level" in changes:
        logging.getLogger().setLevel(settings.logging_level)
    request.state.audit_reason = "; ".join(
        f"{k}: {old!r} -> {new!r}" for k, (old, new) in changes.items()
    )
    return {"changed": {k: {"old": old, "new": new} for k, (old, new) in changes.items()}}
