"""The requests of both clients, built once: method, path, params and body of each
command and query, and how to read its answer.

Everything here is pure (no I/O): `CellClient` and `AsyncCellClient` only send a
`Call` and hand the answer back to `read`, so the two clients cannot drift apart
in what they ask or in how they read an answer.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Collection
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar
from urllib.parse import quote, urlencode

import httpx

from clients.client.config import COMMANDS
from clients.client.errors import (
    Busy,
    CellError,
    CommandResult,
    Forbidden,
    InvalidRequest,
    NotFound,
    Refused,
    ServerError,
    Unauthorized,
    Unreachable,
)

T = TypeVar("T")


@dataclass(frozen=True, slots=True)
class Call(Generic[T]):
    """One HTTP request and how to read its successful answer."""

    method: str
    path: str
    parse: Callable[[httpx.Response], T]
    json: Any = None
    params: dict[str, Any] | None = None
    ok: Collection[int] = field(default=(200, 201, 202))


# --- reading answers ---------------------------------------------------------------


def body_of(response: httpx.Response) -> Any:
    try:
        return response.json()
    except ValueError:
        return response.text


def message_of(body: Any, fallback: str) -> str:
    if isinstance(body, dict):
        for key in ("message", "detail"):
            value = body.get(key)
            if isinstance(value, str) and value:
                return value
            if value:
                return json.dumps(value)
    if isinstance(body, str) and body.strip():
        return body.strip()[:500]
    return fallback


def command_result(response: httpx.Response, body: Any) -> CommandResult:
    data = body if isinstance(body, dict) else {}
    return CommandResult(
        accepted=bool(data.get("accepted", response.status_code == 202)),
        event_id=data.get("event_id"),
        state=str(data.get("state", "")),
        message=message_of(body, f"HTTP {response.status_code}"),
        status_code=response.status_code,
        run_id=data.get("run_id"),
    )


def error_of(response: httpx.Response) -> CellError:
    """The typed exception for a non-success answer, with the server's message."""
    status = response.status_code
    body = body_of(response)
    message = message_of(body, f"HTTP {status} {response.reason_phrase}".strip())
    if status == 401:
        return Unauthorized(message, status_code=status, body=body)
    if status == 403:
        return Forbidden(message, status_code=status, body=body)
    if status == 404:
        return NotFound(message, status_code=status, body=body)
    if status == 409:
        return Refused(command_result(response, body), body=body)
    if status in (400, 413, 422):
        errors = body.get("errors") if isinstance(body, dict) else None
        return InvalidRequest(
            message,
            status_code=status,
            body=body,
            errors=errors if isinstance(errors, list) else None,
        )
    if status == 503:
        retry_after = 1.0
        for candidate in (
            response.headers.get("retry-after"),
            body.get("retry_after") if isinstance(body, dict) else None,
        ):
            try:
                retry_after = float(candidate)  # type: ignore[arg-type]
                break
            except (TypeError, ValueError):
                continue
        return Busy(message, retry_after=retry_after, status_code=status, body=body)
    return ServerError(message, status_code=status, body=body)


def read(call: Call[T], response: httpx.Response) -> T:
    """The parsed answer to `call`, or the typed exception for it."""
    if response.status_code not in call.ok:
        raise error_of(response)
    try:
        return call.parse(response)
    except (ValueError, KeyError, TypeError) as exc:  # e.g. a proxy's HTML page, not the API
        raise ServerError(
            f"unexpected answer to {call.method} {call.path}: {type(exc).__name__}: {exc}",
            status_code=response.status_code,
            body=body_of(response),
        ) from exc


def unreachable(base_url: str, exc: httpx.TransportError, timeout: float) -> Unreachable:
    """The Unreachable for a request that got no answer at all."""
    if isinstance(exc, httpx.TimeoutException):
        return Unreachable(f"no answer from {base_url} within {timeout:g} s ({type(exc).__name__})")
    detail = str(exc) or type(exc).__name__
    return Unreachable(f"cannot reach {base_url}: {detail}")


# What a request meets when the server closed its kept-alive connection as it went out.
_CONNECTION_CLOSED = (httpx.RemoteProtocolError, httpx.ReadError, httpx.WriteError)
_READS = frozenset({"GET", "HEAD", "OPTIONS"})


def may_send_again(call: Call[Any], exc: httpx.TransportError) -> bool:
    """Whether a request that got no answer is sent once more, on a new connection.

    Only a read (a safe method, RFC 9110, 9.2.1), and only when the connection closed
    under it: reading twice changes nothing. A command or a change (POST, PUT, PATCH,
    DELETE) is never sent again, as the server may have taken it: a DELETE sent again
    would answer 404 for a part it had just removed. Its caller is told there was no
    answer.
    """
    return call.method in _READS and isinstance(exc, _CONNECTION_CLOSED)


def _json(response: httpx.Response) -> Any:
    return response.json()


# --- commands: 202 accepted, anything else raises (409 Refused) ----------------------


def command(name: str, body: dict[str, Any] | None = None) -> Call[CommandResult]:
    """POST /<name>, one of COMMANDS."""
    if name not in COMMANDS:
        raise ValueError(f"unknown command {name!r}; commands: {', '.join(COMMANDS)}")
    return Call("POST", f"/{name}", lambda r: command_result(r, body_of(r)), json=body, ok=(202,))


def start(workpiece_id: str | None, contour_matching: bool) -> Call[CommandResult]:
    return command("start", {"contour_matching": contour_matching, "workpiece_id": workpiece_id})


def estop(reason: str | None) -> Call[CommandResult]:
    return command("estop", {"reason": reason} if reason else None)


def jog(axis: str, distance_mm: float) -> Call[CommandResult]:
    return command("jog", {"axis": axis, "distance_mm": distance_mm})


def create_workpiece(
    name: str | None, workpiece_id: str | None, if_new: bool = False
) -> Call[CommandResult]:
    """`if_new`: store the part only if it matches no stored one (the run's result says
    which it matches, `similar`, and `stored`)."""
    body: dict[str, object] = {
        k: v for k, v in (("name", name), ("workpiece_id", workpiece_id)) if v is not None
    }
    if if_new:
        body["if_new"] = True
    return command("create-workpiece", body or None)


# --- queries -----------------------------------------------------------------------


def state() -> Call[dict[str, Any]]:
    return Call("GET", "/state", _json)


def workpieces() -> Call[list[dict[str, Any]]]:
    return Call("GET", "/workpieces", lambda r: r.json()["workpieces"])


def history(limit: int) -> Call[list[dict[str, Any]]]:
    return Call("GET", "/history", lambda r: r.json()["transitions"], params={"limit": limit})


def kpis() -> Call[dict[str, Any]]:
    return Call("GET", "/kpis", _json)


def maintenance() -> Call[dict[str, Any]]:
    return Call("GET", "/maintenance", _json)


def maintenance_done(item: str) -> Call[dict[str, Any]]:
    return Call("POST", f"/maintenance/{quote(item, safe='')}/done", _json)


def glue_refill() -> Call[dict[str, Any]]:
    return Call("POST", "/glue/refill", _json)


def reports(period: str | None = None, limit: int = 50) -> Call[list[dict[str, Any]]]:
    params: dict[str, Any] = {"limit": limit} | ({"period": period} if period else {})
    return Call("GET", "/reports", lambda r: r.json()["reports"], params=params)


def report(report_id: int) -> Call[dict[str, Any]]:
    return Call("GET", f"/reports/{int(report_id)}", _json, params={"format": "json"})


def report_html(report_id: int) -> Call[str]:
    return Call("GET", f"/reports/{int(report_id)}", lambda r: r.text, params={"format": "html"})


def health() -> Call[dict[str, Any]]:
    # 200 whether the devices are ok or degraded; the body says which.
    return Call("GET", "/health", _json)


def allowed(command: str) -> Call[dict[str, Any]]:
    return Call("GET", f"/operations/{quote(command, safe='')}/allowed", _json)


def markers() -> Call[dict[str, Any]]:
    return Call("GET", "/calibration/markers", _json)


def teach_marker(marker: int) -> Call[dict[str, Any]]:
    return Call("POST", f"/calibration/markers/draft/{int(marker)}/teach", _json)


def apply_markers() -> Call[dict[str, Any]]:
    return Call("POST", "/calibration/markers/apply", _json)


def settings() -> Call[dict[str, Any]]:
    return Call("GET", "/settings", _json)


def change_settings(values: dict[str, Any]) -> Call[dict[str, Any]]:
    return Call("PATCH", "/settings", _json, json=values)


def create_order(workpiece_id: str, quantity: int) -> Call[dict[str, Any]]:
    body = {"workpiece_id": workpiece_id, "quantity": quantity}
    return Call("POST", "/orders", _json, json=body)


def orders(state: str | None = None) -> Call[dict[str, Any]]:
    return Call("GET", "/orders", _json, params={"state": state} if state else None)


def order(order_id: str) -> Call[dict[str, Any]]:
    return Call("GET", f"/orders/{quote(order_id, safe='')}", _json)


def close_order(order_id: str) -> Call[dict[str, Any]]:
    return Call("POST", f"/orders/{quote(order_id, safe='')}/close", _json)


def resume_order(order_id: str) -> Call[dict[str, Any]]:
    return Call("POST", f"/orders/{quote(order_id, safe='')}/resume", _json)


def order_report(order_id: str) -> Call[dict[str, Any]]:
    return Call("GET", f"/orders/{quote(order_id, safe='')}/report", _json)


def order_report_csv(order_id: str) -> Call[str]:
    path = f"/orders/{quote(order_id, safe='')}/report"
    return Call("GET", path, lambda r: r.text, params={"format": "csv"})


def ws_ticket() -> Call[str]:
    return Call("POST", "/ws-ticket", lambda r: r.json()["ticket"])


# --- the WebSocket ------------------------------------------------------------------


def ws_url(
    base_url: str, ticket: str, *, after_seq: int | None = None, boot: str | None = None
) -> str:
    """The /ws address for `ticket`, under `base_url` (keeps a path prefix).

    With `after_seq` and `boot` (the last seq received and the snapshot's boot;
    one means nothing without the other) the server replays what came after.
    """
    if (after_seq is None) != (boot is None):
        raise ValueError("after_seq and boot go together (both from the last snapshot)")
    base = httpx.URL(base_url)
    scheme = "wss" if base.scheme == "https" else "ws"
    path = base.path.rstrip("/") + "/ws"
    query: dict[str, str | int] = {"ticket": ticket}
    if after_seq is not None and boot is not None:
        query |= {"after_seq": after_seq, "boot": boot}
    return str(base.copy_with(scheme=scheme, path=path, query=urlencode(query).encode()))
