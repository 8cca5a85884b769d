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

The package is laid out the way httpx splits its clients; import from here,
the modules are an implementation detail:

    config.py        URLs, tokens, the server's state and command names
    errors.py        CommandResult and the exceptions above
    builders.py      each request (method, path, params, body) and how to read
                     its answer: pure, shared by both clients
    wait.py          the decisions of wait_for_state, shared by both clients
    sync_client.py   CellClient (httpx.Client)
    async_client.py  AsyncCellClient (httpx.AsyncClient)
    stream.py        MessageStream: /ws, resumed with after_seq and boot

The client deliberately does not import the server package: it is usable from a
machine that only has httpx and websockets installed.
"""

from __future__ import annotations

from clients.client.async_client import AsyncCellClient
from clients.client.config import (
    ADMIN_TOKEN_FILE,
    CA_FILE_ENV,
    COMMANDS,
    DATA_DIR_ENV,
    DEFAULT_DATA_DIR,
    DEFAULT_URL,
    STATES,
    TOKEN_ENV,
    URL_ENV,
    USER_AGENT,
    WS_MAX_MESSAGE_BYTES,
    normalize_state,
    normalize_url,
    resolve_token,
    trust,
)
from clients.client.errors import (
    Busy,
    CellError,
    CellFaulted,
    CommandResult,
    Forbidden,
    InvalidRequest,
    NotFound,
    Refused,
    ServerError,
    Unauthorized,
    Unreachable,
    WaitTimeout,
)
from clients.client.stream import MessageStream
from clients.client.sync_client import CellClient

__all__ = [
    "ADMIN_TOKEN_FILE",
    "CA_FILE_ENV",
    "COMMANDS",
    "DATA_DIR_ENV",
    "DEFAULT_DATA_DIR",
    "DEFAULT_URL",
    "STATES",
    "TOKEN_ENV",
    "URL_ENV",
    "USER_AGENT",
    "WS_MAX_MESSAGE_BYTES",
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
    "trust",
]
