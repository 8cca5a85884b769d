"""Typed Python clients of the glue cell's HTTP and WebSocket API.

`CellClient` (blocking, for scripts and the `gluectl` CLI) and `AsyncCellClient`
(asyncio, for dashboards and bridges) have the same methods. They exist so that
callers never parse status codes themselves: a command either returns a
`CommandResult` (202, accepted) or raises one typed exception per way it can go
wrong, each carrying the server's own message:

    CellError          the root; anything below, or an unexpected answer (ServerError)
    ├── Refused        409: the state machine refused the command (`.result`)
    ├── Unauthorized   401: no token, or an unknown or revoked one
    ├── Forbidden      403: the token's role is too low (the message names the role)
    ├── Unreachable    no answer: connection refused, DNS, timeout
    ├── InvalidRequest 422: a field is invalid (the server's detail, `.errors`)
    │   └── NotFound   404: e.g. an unknown operation name
    ├── Busy           503: the event queue is full (`.retry_after` seconds)
    ├── WaitTimeout    `wait_for_state` ran out of time (`.last_state`)
    └── CellFaulted    `wait_for_state` found the cell in ERROR instead

`AsyncCellClient.messages()` follows `/ws` across reconnects: it reconnects
with the last `seq` it saw and the server's `boot`, and the server replays what
went by meanwhile from its ring of recent messages, so the consumer sees every
message exactly once. When the gap is too old for the ring, or the server
restarted, the fresh snapshot says how many sequence numbers were `missed`, and
the consumer knows to resynchronise from it instead of silently losing events.

The client deliberately does not import the server package: it is usable from a
machine that only has httpx and websockets installed.
"""

from __future__ import annotations

import asyncio
import json
import os
import random
import time
from collections.abc import AsyncGenerator, AsyncIterator, Callable, Collection, Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, Generic, Self, TypeVar
from urllib.parse import quote, urlencode

import httpx
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidURI

__all__ = [
    "DATA_DIR_ENV",
    "DEFAULT_URL",
    "STATES",
    "TOKEN_ENV",
    "URL_ENV",
    "AsyncCellClient",
    "Busy",
    "CellClient",
    "CellError",
    "CellFaulted",
    "CommandResult",
    "Forbidden",
    "InvalidRequest",
    "MessageStream",
    "NotFound",
    "Refused",
    "ServerError",
    "Unauthorized",
    "Unreachable",
    "WaitTimeout",
    "normalize_state",
    "normalize_url",
    "resolve_token",
]

DEFAULT_URL = "http://127.0.0.1:8000"
URL_ENV = "GLUE_CELL_URL"
TOKEN_ENV = "GLUE_CELL_TOKEN"
DATA_DIR_ENV = "GLUE_APP_DATA_PATH"  # the server's own data directory setting
DEFAULT_DATA_DIR = "data"
ADMIN_TOKEN_FILE = "admin.token"

# The machine's states, as the server names them (server/core/transitions.py).
STATES = (
    "INITIALIZING",
    "IDLE",
    "CALIBRATING_ROBOT",
    "CALIBRATING_CAMERA",
    "EXECUTING_TRAJECTORY",
    "CREATING_WORKPIECE",
    "PAUSED",
    "ERROR",
)
USER_AGENT = "glue-cell-client/0.1"
WS_MAX_MESSAGE_BYTES = 16 * 2**20

T = TypeVar("T")


# --- results and errors --------------------------------------------------------


@dataclass(frozen=True, slots=True)
class CommandResult:
    """The worker's decision on a command (202 accepted, 409 refused)."""

    accepted: bool
    event_id: str | None
    state: str  # the state after the decision
    message: str
    status_code: int

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


class CellError(Exception):
    """Root of every error the clients raise; `str(error)` is the server's message."""

    def __init__(self, message: str, *, status_code: int | None = None, body: Any = None) -> None:
        super().__init__(message)
        self.message = message
        self.status_code = status_code
        self.body = body

    def as_dict(self) -> dict[str, Any]:
        """A JSON-able description, for machine-readable error output."""
        return {
            "error": type(self).__name__,
            "status_code": self.status_code,
            "message": self.message,
        }


class Refused(CellError):
    """409: the command is not allowed in the current state; `result` says which state."""

    def __init__(self, result: CommandResult, *, body: Any = None) -> None:
        super().__init__(result.message, status_code=result.status_code, body=body)
        self.result = result

    def as_dict(self) -> dict[str, Any]:
        return {**super().as_dict(), **self.result.as_dict()}


class Unauthorized(CellError):
    """401: no token was sent, or the token is unknown or revoked."""


class Forbidden(CellError):
    """403: the token's role is too low (or the address is not in trusted_networks)."""


class Unreachable(CellError):
    """The server did not answer: connection refused, name not resolved, or a timeout."""


class InvalidRequest(CellError):
    """422 (or 400/413): the request was malformed; `errors` lists the fields."""

    def __init__(
        self,
        message: str,
        *,
        status_code: int | None = 422,
        body: Any = None,
        errors: list[dict[str, Any]] | None = None,
    ) -> None:
        super().__init__(message, status_code=status_code, body=body)
        self.errors = errors or []

    def as_dict(self) -> dict[str, Any]:
        return {**super().as_dict(), "errors": self.errors}


class NotFound(InvalidRequest):
    """404: the request names something the server does not have."""


class Busy(CellError):
    """503: the event queue is full (nothing was changed); retry after `retry_after` s."""

    def __init__(
        self, message: str, *, retry_after: float = 1.0, status_code: int = 503, body: Any = None
    ) -> None:
        super().__init__(message, status_code=status_code, body=body)
        self.retry_after = retry_after

    def as_dict(self) -> dict[str, Any]:
        return {**super().as_dict(), "retry_after": self.retry_after}


class ServerError(CellError):
    """Any other answer the API does not document for the call (e.g. 500)."""


class WaitTimeout(CellError):
    """`wait_for_state` ran out of time; `last_state` is the last GET /state seen."""

    def __init__(self, message: str, last_state: dict[str, Any] | None) -> None:
        super().__init__(message)
        self.last_state = last_state

    def as_dict(self) -> dict[str, Any]:
        state = self.last_state["state"] if self.last_state else None
        return {**super().as_dict(), "state": state}


class CellFaulted(CellError):
    """`wait_for_state` found the cell in ERROR while it waited for another state.

    Waiting on would only run into the timeout: leaving ERROR takes a reset.
    """

    def __init__(self, message: str, last_state: dict[str, Any]) -> None:
        super().__init__(message)
        self.last_state = last_state

    def as_dict(self) -> dict[str, Any]:
        return {**super().as_dict(), "state": self.last_state.get("state")}


# --- configuration helpers -------------------------------------------------------


def resolve_token(
    option: str | None,
    env: str = TOKEN_ENV,
    data_dir: str | os.PathLike[str] | None = None,
) -> str | None:
    """The token to use: `option`, else `$GLUE_CELL_TOKEN`, else `<data dir>/admin.token`.

    The data directory is `data_dir`, else `$GLUE_APP_DATA_PATH` (the server's own
    setting, so a CLI on the server's host finds the token the server wrote), else
    `./data`. None when there is no token anywhere: requests then answer 401.
    """
    if option and option.strip():
        return option.strip()
    from_env = os.environ.get(env, "").strip()
    if from_env:
        return from_env
    directory = Path(data_dir or os.environ.get(DATA_DIR_ENV) or DEFAULT_DATA_DIR)
    try:
        token = (directory / ADMIN_TOKEN_FILE).read_text(encoding="utf-8").strip()
    except OSError:  # missing, or not readable by this user (it is mode 0600)
        return None
    return token or None


def normalize_url(url: str) -> str:
    """`localhost:8000` → `http://localhost:8000`; no trailing slash."""
    url = url.strip()
    if "://" not in url:
        url = f"http://{url}"
    return url.rstrip("/")


def normalize_state(state: str) -> str:
    """`idle` → `IDLE`; ValueError naming the known states for anything else."""
    canonical = state.strip().upper().replace("-", "_")
    if canonical not in STATES:
        raise ValueError(f"unknown state {state!r}; states: {', '.join(STATES)}")
    return canonical


# --- requests, shared by both clients ------------------------------------------


@dataclass(frozen=True, slots=True)
class _Call(Generic[T]):
    """One HTTP request and how to read its successful answer."""

    method: str
    path: str
    parse: Callable[[httpx.Response], T]
    json: Any = None
    params: dict[str, Any] | None = None
    ok: Collection[int] = field(default=(200, 201, 202))


def _body(response: httpx.Response) -> Any:
    try:
        return response.json()
    except ValueError:
        return response.text


def _message(body: Any, fallback: str) -> str:
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


def _command_result(response: httpx.Response, body: Any) -> CommandResult:
    data = body if isinstance(body, dict) else {}
    return CommandResult(
        accepted=bool(data.get("accepted", response.status_code == 202)),
        event_id=data.get("event_id"),
        state=str(data.get("state", "")),
        message=_message(body, f"HTTP {response.status_code}"),
        status_code=response.status_code,
    )


def _error(response: httpx.Response) -> CellError:
    """The typed exception for a non-success answer, with the server's message."""
    status = response.status_code
    body = _body(response)
    message = _message(body, f"HTTP {status} {response.reason_phrase}".strip())
    if status == 401:
        return Unauthorized(message, status_code=status, body=body)
    if status == 403:
        return Forbidden(message, status_code=status, body=body)
    if status == 404:
        return NotFound(message, status_code=status, body=body)
    if status == 409:
        return Refused(_command_result(response, body), body=body)
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


def _read(call: _Call[T], response: httpx.Response) -> T:
    if response.status_code not in call.ok:
        raise _error(response)
    try:
        return call.parse(response)
    except (ValueError, KeyError, TypeError) as exc:  # e.g. a proxy's HTML page, not the API
        raise ServerError(
            f"unexpected answer to {call.method} {call.path}: {type(exc).__name__}: {exc}",
            status_code=response.status_code,
            body=_body(response),
        ) from exc


def _unreachable(base_url: str, exc: httpx.TransportError, timeout: float) -> Unreachable:
    if isinstance(exc, httpx.TimeoutException):
        return Unreachable(f"no answer from {base_url} within {timeout:g} s ({type(exc).__name__})")
    detail = str(exc) or type(exc).__name__
    return Unreachable(f"cannot reach {base_url}: {detail}")


def _json(response: httpx.Response) -> Any:
    return response.json()


def _command(path: str, body: dict[str, Any] | None = None) -> _Call[CommandResult]:
    return _Call("POST", path, lambda r: _command_result(r, _body(r)), json=body, ok=(202,))


def _start(workpiece_id: str | None, contour_matching: bool) -> _Call[CommandResult]:
    return _command("/start", {"contour_matching": contour_matching, "workpiece_id": workpiece_id})


def _estop(reason: str | None) -> _Call[CommandResult]:
    return _command("/estop", {"reason": reason} if reason else None)


def _create_workpiece(name: str | None, workpiece_id: str | None) -> _Call[CommandResult]:
    body = {k: v for k, v in (("name", name), ("workpiece_id", workpiece_id)) if v is not None}
    return _command("/create-workpiece", body or None)


def _state() -> _Call[dict[str, Any]]:
    return _Call("GET", "/state", _json)


def _workpieces() -> _Call[list[dict[str, Any]]]:
    return _Call("GET", "/workpieces", lambda r: r.json()["workpieces"])


def _history(limit: int) -> _Call[list[dict[str, Any]]]:
    return _Call("GET", "/history", lambda r: r.json()["transitions"], params={"limit": limit})


def _kpis() -> _Call[dict[str, Any]]:
    return _Call("GET", "/kpis", _json)


def _health() -> _Call[dict[str, Any]]:
    # 200 whether the devices are ok or degraded; the body says which.
    return _Call("GET", "/health", _json)


def _allowed(command: str) -> _Call[dict[str, Any]]:
    return _Call("GET", f"/operations/{quote(command, safe='')}/allowed", _json)


def _ticket() -> _Call[str]:
    return _Call("POST", "/ws-ticket", lambda r: r.json()["ticket"])


class _StateWait:
    """The decisions of `wait_for_state`, shared by the blocking and async clients."""

    def __init__(self, target: str, timeout: float, fail_on: Iterable[str]) -> None:
        self.target = normalize_state(target)
        self.timeout = timeout
        self.deadline = time.monotonic() + timeout
        self.fail_on = {normalize_state(s) for s in fail_on} - {self.target}
        self.last: dict[str, Any] | None = None

    def reached(self, snapshot: dict[str, Any]) -> bool:
        """True at the target; raises CellFaulted in a fail state.

        A fail state counts whenever it is seen, even on the first poll: an
        operation can fail within milliseconds of being accepted, before any
        poll, and a script that started it must not wait for a reset instead.
        """
        self.last = snapshot
        state = snapshot.get("state")
        if state == self.target:
            return True
        if state in self.fail_on:
            fault = snapshot.get("error") or snapshot.get("stop_reason") or {}
            why = f": {fault['message']}" if fault.get("message") else ""
            raise CellFaulted(f"the cell is in {state}, waiting for {self.target}{why}", snapshot)
        return False

    def remaining(self) -> float:
        return self.deadline - time.monotonic()

    def expired(self) -> WaitTimeout:
        where = f"; the cell is in {self.last['state']}" if self.last else ""
        return WaitTimeout(
            f"timed out after {self.timeout:g} s waiting for {self.target}{where}", self.last
        )


def _headers(token: str | None) -> dict[str, str]:
    headers = {"User-Agent": USER_AGENT}
    if token:
        headers["Authorization"] = f"Bearer {token}"
    return headers


# --- the blocking client -----------------------------------------------------------


class CellClient:
    """Blocking client (httpx.Client). Use as a context manager, or call close()."""

    def __init__(
        self,
        base_url: str = DEFAULT_URL,
        token: str | None = None,
        *,
        timeout: float = 10.0,
    ) -> None:
        self.base_url = normalize_url(base_url)
        self.timeout = timeout
        self._http = httpx.Client(base_url=self.base_url, headers=_headers(token), timeout=timeout)

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def _send(self, call: _Call[T]) -> T:
        try:
            response = self._http.request(
                call.method, call.path, json=call.json, params=call.params
            )
        except httpx.TransportError as exc:
            raise _unreachable(self.base_url, exc, self.timeout) from exc
        return _read(call, response)

    # commands: a CommandResult when accepted (202), Refused when refused (409)

    def start(
        self, workpiece_id: str | None = None, contour_matching: bool = True
    ) -> CommandResult:
        """Start spraying (IDLE → EXECUTING_TRAJECTORY)."""
        return self._send(_start(workpiece_id, contour_matching))

    def pause(self) -> CommandResult:
        """Hold the trajectory at its next waypoint, glue off."""
        return self._send(_command("/pause"))

    def resume(self) -> CommandResult:
        """Continue a paused trajectory from where it held."""
        return self._send(_command("/resume"))

    def cancel(self) -> CommandResult:
        """Stop the running operation at once and return to IDLE."""
        return self._send(_command("/cancel"))

    def estop(self, reason: str | None = None) -> CommandResult:
        """Software stop: valve closed and robot stopped, then ERROR (any role)."""
        return self._send(_estop(reason))

    def reset(self) -> CommandResult:
        """Leave ERROR for IDLE once every device answers (maintenance role)."""
        return self._send(_command("/reset"))

    def calibrate_robot(self) -> CommandResult:
        """Fit the image → robot map from the ArUco markers (maintenance role)."""
        return self._send(_command("/calibrate-robot"))

    def calibrate_camera(self) -> CommandResult:
        """Calibrate the camera's intrinsics from chessboard views (maintenance role)."""
        return self._send(_command("/calibrate-camera"))

    def create_workpiece(
        self, name: str | None = None, workpiece_id: str | None = None
    ) -> CommandResult:
        """Capture the part on the table into the library."""
        return self._send(_create_workpiece(name, workpiece_id))

    # queries

    def state(self) -> dict[str, Any]:
        """GET /state: state, operation and progress, the fault if any."""
        return self._send(_state())

    def workpieces(self) -> list[dict[str, Any]]:
        """The workpiece library."""
        return self._send(_workpieces())

    def history(self, limit: int = 20) -> list[dict[str, Any]]:
        """The latest `limit` transitions, newest first."""
        return self._send(_history(limit))

    def kpis(self) -> dict[str, Any]:
        """The current shift's KPIs and OEE."""
        return self._send(_kpis())

    def health(self) -> dict[str, Any]:
        """Each device's link and the worker's figures (needs no token)."""
        return self._send(_health())

    def allowed(self, command: str) -> dict[str, Any]:
        """Whether `command` would be accepted now: `allowed`, `state`, `reason`."""
        return self._send(_allowed(command))

    def wait_for_state(
        self,
        state: str,
        timeout: float,
        *,
        poll_interval: float = 0.1,
        fail_on: Iterable[str] = ("ERROR",),
    ) -> dict[str, Any]:
        """Poll GET /state until the cell is in `state`; returns that snapshot.

        Raises WaitTimeout after `timeout` seconds, and CellFaulted as soon as the
        cell is seen in a `fail_on` state (ERROR: only a reset leaves it, so waiting
        on would just run into the timeout); pass `fail_on=()` to wait through it,
        e.g. for someone else's reset. Polling can miss a state shorter than
        `poll_interval`.
        """
        wait = _StateWait(state, timeout, fail_on)
        while True:
            if wait.reached(self.state()):
                assert wait.last is not None
                return wait.last
            remaining = wait.remaining()
            if remaining <= 0:
                raise wait.expired()
            time.sleep(min(poll_interval, remaining))


# --- the asyncio client ------------------------------------------------------------


class AsyncCellClient:
    """Asyncio client (httpx.AsyncClient), the same methods as CellClient, plus `messages`."""

    def __init__(
        self,
        base_url: str = DEFAULT_URL,
        token: str | None = None,
        *,
        timeout: float = 10.0,
    ) -> None:
        self.base_url = normalize_url(base_url)
        self.timeout = timeout
        self.token = token
        self._http = httpx.AsyncClient(
            base_url=self.base_url, headers=_headers(token), timeout=timeout
        )

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        await self._http.aclose()

    async def _send(self, call: _Call[T]) -> T:
        try:
            response = await self._http.request(
                call.method, call.path, json=call.json, params=call.params
            )
        except httpx.TransportError as exc:
            raise _unreachable(self.base_url, exc, self.timeout) from exc
        return _read(call, response)

    async def start(
        self, workpiece_id: str | None = None, contour_matching: bool = True
    ) -> CommandResult:
        """Start spraying (IDLE → EXECUTING_TRAJECTORY)."""
        return await self._send(_start(workpiece_id, contour_matching))

    async def pause(self) -> CommandResult:
        """Hold the trajectory at its next waypoint, glue off."""
        return await self._send(_command("/pause"))

    async def resume(self) -> CommandResult:
        """Continue a paused trajectory from where it held."""
        return await self._send(_command("/resume"))

    async def cancel(self) -> CommandResult:
        """Stop the running operation at once and return to IDLE."""
        return await self._send(_command("/cancel"))

    async def estop(self, reason: str | None = None) -> CommandResult:
        """Software stop: valve closed and robot stopped, then ERROR (any role)."""
        return await self._send(_estop(reason))

    async def reset(self) -> CommandResult:
        """Leave ERROR for IDLE once every device answers (maintenance role)."""
        return await self._send(_command("/reset"))

    async def calibrate_robot(self) -> CommandResult:
        """Fit the image → robot map from the ArUco markers (maintenance role)."""
        return await self._send(_command("/calibrate-robot"))

    async def calibrate_camera(self) -> CommandResult:
        """Calibrate the camera's intrinsics from chessboard views (maintenance role)."""
        return await self._send(_command("/calibrate-camera"))

    async def create_workpiece(
        self, name: str | None = None, workpiece_id: str | None = None
    ) -> CommandResult:
        """Capture the part on the table into the library."""
        return await self._send(_create_workpiece(name, workpiece_id))

    async def state(self) -> dict[str, Any]:
        """GET /state: state, operation and progress, the fault if any."""
        return await self._send(_state())

    async def workpieces(self) -> list[dict[str, Any]]:
        """The workpiece library."""
        return await self._send(_workpieces())

    async def history(self, limit: int = 20) -> list[dict[str, Any]]:
        """The latest `limit` transitions, newest first."""
        return await self._send(_history(limit))

    async def kpis(self) -> dict[str, Any]:
        """The current shift's KPIs and OEE."""
        return await self._send(_kpis())

    async def health(self) -> dict[str, Any]:
        """Each device's link and the worker's figures (needs no token)."""
        return await self._send(_health())

    async def allowed(self, command: str) -> dict[str, Any]:
        """Whether `command` would be accepted now: `allowed`, `state`, `reason`."""
        return await self._send(_allowed(command))

    async def wait_for_state(
        self,
        state: str,
        timeout: float,
        *,
        poll_interval: float = 0.1,
        fail_on: Iterable[str] = ("ERROR",),
    ) -> dict[str, Any]:
        """Poll GET /state until the cell is in `state` (see CellClient.wait_for_state)."""
        wait = _StateWait(state, timeout, fail_on)
        while True:
            if wait.reached(await self.state()):
                assert wait.last is not None
                return wait.last
            remaining = wait.remaining()
            if remaining <= 0:
                raise wait.expired()
            await asyncio.sleep(min(poll_interval, remaining))

    async def ws_ticket(self) -> str:
        """A one-shot ticket for /ws (valid a few seconds, usable once)."""
        return await self._send(_ticket())

    def ws_url(self, ticket: str, *, after_seq: int | None = None, boot: str | None = None) -> str:
        """The /ws address for `ticket`, under the same base URL (keeps a path prefix).

        With `after_seq` and `boot` (the last seq received and the snapshot's boot;
        one means nothing without the other) the server replays what came after.
        """
        if (after_seq is None) != (boot is None):
            raise ValueError("after_seq and boot go together (both from the last snapshot)")
        base = httpx.URL(self.base_url)
        scheme = "wss" if base.scheme == "https" else "ws"
        path = base.path.rstrip("/") + "/ws"
        query: dict[str, str | int] = {"ticket": ticket}
        if after_seq is not None and boot is not None:
            query |= {"after_seq": after_seq, "boot": boot}
        return str(base.copy_with(scheme=scheme, path=path, query=urlencode(query).encode()))

    def messages(
        self,
        types: Iterable[str] | None = None,
        *,
        reconnect: bool = True,
        initial_backoff: float = 0.2,
        max_backoff: float = 5.0,
    ) -> MessageStream:
        """Follow /ws: the snapshot, then every message (of `types`, if given), in seq order.

        See MessageStream for what happens across reconnects.
        """
        return MessageStream(
            self,
            types,
            reconnect=reconnect,
            initial_backoff=initial_backoff,
            max_backoff=max_backoff,
        )


def _refusal(code: int | None, reason: str) -> CellError:
    """The typed error for a /ws close before the snapshot (close codes in docs/api.md)."""
    message = f"/ws closed ({code}): {reason}"
    if code == 4401:
        return Unauthorized(message, status_code=code)
    if code == 1013:  # too many clients
        return Busy(message, retry_after=1.0, status_code=code)
    return Unreachable(message, status_code=code)


class MessageStream:
    """An async iterator over /ws messages that survives reconnects.

    Each (re)connection takes a fresh one-shot ticket (POST /ws-ticket). The first
    item is the server's snapshot, then every message in `seq` order. When the
    connection drops (slow consumer 4001, server restart, network) the stream
    waits (backoff doubling from `initial_backoff` to `max_backoff`, with jitter)
    and reconnects with `after_seq` (the last seq seen) and `boot` (the server's
    numbering), and yields the new snapshot as
    `{"type": "snapshot", "resumed": True, "missed": N, ...}`:

    - the server still held every message after the last one seen (its ring of
      recent messages): N is 0, the snapshot has `"replayed": K`, and the K
      messages that went by follow it, oldest first, then live ones. So every
      message is yielded exactly once. The replayed ones are older than the
      snapshot (their seq is at or below its seq): a consumer that applied them
      all is where the snapshot is, and may ignore the snapshot;
    - the gap is older than the ring: N seq numbers went by unseen and none
      follow; resynchronise from the snapshot;
    - the server restarted (another `boot`; seq starts again at 1): N counts the
      new server's messages and `restarted` is True.

    Against a server without replay (no `boot` in its snapshot) N is computed
    here, as the difference of seq numbers.

    `types` filters on this side, so `missed` stays exact and `replayed` counts
    every type; snapshots always pass.
    Errors while making the *first* connection are raised (Unreachable,
    Unauthorized, Busy for close 1013 "too many clients", ...); afterwards only
    Unauthorized and Forbidden from the ticket request are (a revoked token will
    not come back), everything else is retried until the consumer stops iterating.

    Stop with `break` (the socket is closed when the stream is collected), or
    deterministically with `aclose()` / `async with stream:`.
    """

    def __init__(
        self,
        client: AsyncCellClient,
        types: Iterable[str] | None,
        *,
        reconnect: bool,
        initial_backoff: float,
        max_backoff: float,
    ) -> None:
        self._client = client
        self.types = frozenset(types) if types is not None else None
        self.reconnect = reconnect
        self.initial_backoff = initial_backoff
        self.max_backoff = max_backoff
        self.last_seq: int | None = None
        self.boot: str | None = None  # the server's numbering that last_seq belongs to
        self.reconnects = 0
        self.last_close: tuple[int | None, str] | None = None  # (code, reason) of the last drop
        self._generator = self._run()

    def __aiter__(self) -> AsyncIterator[dict[str, Any]]:
        return self

    async def __anext__(self) -> dict[str, Any]:
        return await self._generator.__anext__()

    async def aclose(self) -> None:
        await self._generator.aclose()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.aclose()

    def _wanted(self, message: dict[str, Any]) -> bool:
        return self.types is None or message.get("type") in self.types

    async def _open(self) -> ClientConnection:
        ticket = await self._client.ws_ticket()
        # Resume where we were: the server replays what came after last_seq, if it can.
        if self.last_seq is not None and self.boot is not None:
            url = self._client.ws_url(ticket, after_seq=self.last_seq, boot=self.boot)
        else:
            url = self._client.ws_url(ticket)
        try:
            return await connect(
                url,
                open_timeout=self._client.timeout,
                close_timeout=2,
                max_size=WS_MAX_MESSAGE_BYTES,
                user_agent_header=USER_AGENT,
            )
        except (OSError, TimeoutError, InvalidHandshake, InvalidURI) as exc:
            raise Unreachable(f"cannot open {url.split('?')[0]}: {exc}") from exc

    def _resumed(self, snapshot: dict[str, Any]) -> dict[str, Any]:
        """Mark a snapshot after a reconnect with how much went by unseen."""
        seq = int(snapshot.get("seq", 0))
        assert self.last_seq is not None
        marks: dict[str, Any] = {"resumed": True}
        boot = snapshot.get("boot")
        other_boot = self.boot is not None and boot is not None and boot != self.boot
        if other_boot or seq < self.last_seq:  # a new server process: numbering started again
            marks["missed"] = int(snapshot.get("missed", seq))
            marks["restarted"] = True
        elif "replayed" in snapshot:  # everything since last_seq follows this snapshot
            marks["missed"] = 0
        elif "missed" in snapshot:  # the server could not fill the gap
            marks["missed"] = int(snapshot["missed"])
        else:  # a server without replay
            marks["missed"] = seq - self.last_seq
        return {**snapshot, **marks}

    async def _run(self) -> AsyncGenerator[dict[str, Any], None]:
        backoff = self.initial_backoff
        connected_once = False
        while True:
            try:
                websocket = await self._open()
            except (Unauthorized, Forbidden):
                raise
            except CellError:
                if not connected_once or not self.reconnect:
                    raise
                await self._pause(backoff)
                backoff = min(backoff * 2, self.max_backoff)
                continue
            try:
                async with websocket:
                    snapshot = json.loads(await websocket.recv())
                    if snapshot.get("type") != "snapshot":
                        raise ServerError(f"/ws did not start with a snapshot: {snapshot!r:.200}")
                    if connected_once:
                        self.reconnects += 1
                        snapshot = self._resumed(snapshot)
                    connected_once = True
                    backoff = self.initial_backoff
                    if snapshot.get("missed") != 0 or "replayed" not in snapshot:
                        self.last_seq = int(snapshot.get("seq", 0))
                    # else last_seq stays: the replay that follows starts at last_seq + 1.
                    self.boot = snapshot.get("boot")
                    yield snapshot
                    async for raw in websocket:
                        message = json.loads(raw)
                        seq = message.get("seq")
                        if isinstance(seq, int):
                            if seq <= self.last_seq:  # already seen (never expected)
                                continue
                            self.last_seq = seq
                        if self._wanted(message):
                            yield message
                self.last_close = (websocket.close_code, websocket.close_reason or "")
            except ConnectionClosed as closed:
                received = closed.rcvd
                code = received.code if received else None
                reason = (received.reason if received else "") or "connection lost"
                self.last_close = (code, reason)
                if not connected_once:  # refused before the first snapshot: say why
                    raise _refusal(code, reason) from closed
                if code == 1003:
                    # The resume request itself was refused (never expected): start
                    # afresh next time rather than be refused on every attempt.
                    self.boot = None
            except (OSError, TimeoutError, ValueError) as exc:
                self.last_close = (None, f"{type(exc).__name__}: {exc}")
                if not connected_once:
                    raise Unreachable(f"/ws failed: {self.last_close[1]}") from exc
            if not self.reconnect:
                return
            await self._pause(backoff)
            backoff = min(backoff * 2, self.max_backoff)

    @staticmethod
    async def _pause(backoff: float) -> None:
        # Jitter, so a fleet of dashboards does not reconnect in lockstep after a restart.
        await asyncio.sleep(backoff * random.uniform(0.8, 1.2))
