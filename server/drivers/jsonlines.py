"""JSON-lines framing and JSON-RPC 2.0 message helpers for the robot controller link.

Framing on the wire: one JSON object per line, UTF-8 encoded, terminated by a
single "\\n" (a trailing "\\r" is tolerated and stripped). Encoded messages never
contain a raw newline because JSON escapes control characters inside strings,
so the newline is an unambiguous frame boundary. Empty or blank lines are
skipped. A line longer than `max_line_bytes` (1 MiB by default) is refused with
`LineTooLong`, because a peer that never sends a newline would otherwise grow
our buffer without bound.

This module does no I/O: the client (`robot_jsonrpc`) and the simulator
(`sim.robot_sim`) both feed it the bytes they read, which keeps the framing
rules in one place and lets them be tested with plain byte strings.

Error codes: the JSON-RPC standard ones (-32700 parse error, -32600 invalid
request, -32601 method not found, -32602 invalid params, -32603 internal
error) plus the controller's application codes `WORKSPACE_VIOLATION` (1001)
and `INJECTED_FAILURE` (1002, used by the simulator's fault injection).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

JSONRPC_VERSION = "2.0"
MAX_LINE_BYTES = 1 << 20

PARSE_ERROR = -32700
INVALID_REQUEST = -32600
METHOD_NOT_FOUND = -32601
INVALID_PARAMS = -32602
INTERNAL_ERROR = -32603
WORKSPACE_VIOLATION = 1001
INJECTED_FAILURE = 1002

RequestId = int | str | None


class FramingError(Exception):
    """The byte stream broke the line framing rules."""


class LineTooLong(FramingError):
    """A line grew past the limit; the decoder dropped it and resumes at the next newline.

    `messages` holds the good messages decoded from the same chunk, so a caller
    that wants to carry on after logging the overlong line loses nothing else.
    """

    def __init__(self, limit: int, messages: list[Any] | None = None) -> None:
        self.limit = limit
        self.messages: list[Any] = messages if messages is not None else []
        super().__init__(f"a message line exceeded {limit} bytes without a newline")


@dataclass(frozen=True)
class MalformedLine:
    """A complete line that is not valid UTF-8 JSON, returned instead of raising.

    Returned as a value so one bad line from a peer never tears down the reader
    loop: the caller decides whether to log it, count it or answer -32700.
    """

    raw: bytes
    reason: str


class JsonRpcError(Exception):
    """A JSON-RPC error to send back; raised by request handlers in the simulator."""

    def __init__(self, code: int, message: str, data: Any = None) -> None:
        self.code = code
        self.message = message
        self.data = data
        super().__init__(f"JSON-RPC error {code}: {message}")


def _reject_constant(name: str) -> Any:
    """Refuse NaN/Infinity, which Python's json accepts but JSON does not."""
    raise ValueError(f"{name} is not valid JSON")


def decode_line(line: bytes) -> Any | MalformedLine:
    """Decode one frame (without its newline) into a JSON value or a MalformedLine."""
    try:
        text = line.decode("utf-8")
    except UnicodeDecodeError as exc:
        return MalformedLine(line, f"not valid UTF-8: {exc}")
    try:
        return json.loads(text, parse_constant=_reject_constant)
    except ValueError as exc:  # JSONDecodeError is a ValueError
        return MalformedLine(line, f"not valid JSON: {exc}")


class LineDecoder:
    """Turns arbitrary chunks of bytes into complete decoded messages.

    Bytes are buffered until a newline arrives, so a message (or a multi-byte
    UTF-8 character) split across reads is reassembled, and several messages
    in one read all come out in order.
    """

    def __init__(self, max_line_bytes: int = MAX_LINE_BYTES) -> None:
        if max_line_bytes < 1:
            raise ValueError("max_line_bytes must be positive")
        self.max_line_bytes = max_line_bytes
        self._buffer = bytearray()
        self._scan_from = 0  # no newline before this index of the buffer
        self._discarding = False  # inside an overlong line, dropping bytes until "\n"

    @property
    def buffered(self) -> int:
        """Bytes held for an incomplete line (for diagnostics)."""
        return len(self._buffer)

    def feed(self, data: bytes) -> list[Any | MalformedLine]:
        """Add bytes; return every message completed by them, in order.

        Raises LineTooLong (carrying the chunk's good messages) when a line
        exceeds the limit; that line is dropped and decoding resumes after its
        newline, so a caller may log the error and keep reading.
        """
        buffer = self._buffer
        buffer += data
        messages: list[Any | MalformedLine] = []
        overlong = False
        position = 0
        while True:
            newline = buffer.find(b"\n", max(position, self._scan_from))
            if newline < 0:
                break
            line = bytes(buffer[position:newline])
            position = newline + 1
            if self._discarding:
                self._discarding = False
                continue
            if len(line) > self.max_line_bytes:
                overlong = True
                continue
            line = line.rstrip(b"\r")
            if line.strip():
                messages.append(decode_line(line))
        del buffer[:position]
        self._scan_from = len(buffer)
        if self._discarding or len(buffer) > self.max_line_bytes:
            overlong = overlong or not self._discarding
            self._discarding = True
            buffer.clear()
            self._scan_from = 0
        if overlong:
            raise LineTooLong(self.max_line_bytes, messages)
        return messages

    def reset(self) -> None:
        """Forget any partial line (e.g. after a reconnect)."""
        self._buffer.clear()
        self._scan_from = 0
        self._discarding = False


def encode_message(obj: Any) -> bytes:
    """One JSON value as a UTF-8 line ending in "\\n"; refuses NaN and Infinity."""
    return (
        json.dumps(obj, ensure_ascii=False, separators=(",", ":"), allow_nan=False).encode("utf-8")
        + b"\n"
    )


def make_request(
    method: str, params: list[Any] | dict[str, Any] | None = None, request_id: RequestId = None
) -> dict[str, Any]:
    """A request (or a notification when `request_id` is None)."""
    message: dict[str, Any] = {"jsonrpc": JSONRPC_VERSION, "method": method}
    if params is not None:
        message["params"] = params
    if request_id is not None:
        message["id"] = request_id
    return message


def make_result(request_id: RequestId, result: Any) -> dict[str, Any]:
    """A success response."""
    return {"jsonrpc": JSONRPC_VERSION, "id": request_id, "result": result}


def make_error(request_id: RequestId, code: int, message: str, data: Any = None) -> dict[str, Any]:
    """An error response; `request_id` is None when the request could not be read."""
    error: dict[str, Any] = {"code": code, "message": message}
    if data is not None:
        error["data"] = data
    return {"jsonrpc": JSONRPC_VERSION, "id": request_id, "error": error}


@dataclass(frozen=True)
class Request:
    """A validated incoming request; `is_notification` requests get no answer."""

    method: str
    params: list[Any] | dict[str, Any]
    id: RequestId
    is_notification: bool


def parse_request(message: Any) -> Request:
    """Validate a decoded message as a single JSON-RPC request.

    Raises JsonRpcError(INVALID_REQUEST) for anything else, including batches
    (arrays), which this controller does not support.
    """
    if isinstance(message, list):
        raise JsonRpcError(INVALID_REQUEST, "batch requests are not supported")
    if not isinstance(message, dict):
        raise JsonRpcError(INVALID_REQUEST, "a request must be a JSON object")
    if message.get("jsonrpc") != JSONRPC_VERSION:
        raise JsonRpcError(INVALID_REQUEST, 'a request must have "jsonrpc": "2.0"')
    method = message.get("method")
    if not isinstance(method, str) or not method:
        raise JsonRpcError(INVALID_REQUEST, 'a request must have a string "method"')
    params = message.get("params", [])
    if not isinstance(params, list | dict):
        raise JsonRpcError(INVALID_REQUEST, '"params" must be an array or an object')
    request_id = message.get("id")
    if isinstance(request_id, bool) or not isinstance(request_id, int | str | None):
        raise JsonRpcError(INVALID_REQUEST, '"id" must be a number, a string or null')
    if isinstance(request_id, float) and not math.isfinite(request_id):
        raise JsonRpcError(INVALID_REQUEST, '"id" must be finite')
    return Request(method, params, request_id, is_notification="id" not in message)
