"""What the clients return for an accepted command, and what they raise otherwise.

One exception class per way a call can go wrong, so that callers never parse
status codes themselves; each carries the server's own message (the tree is in
the package's docstring, `clients/client/__init__.py`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any


@dataclass(frozen=True, slots=True)
class CommandResult:
    """The worker's decision on a command (202 accepted, 409 refused)."""

    accepted: bool
    event_id: str | None
    state: str  # the state after the decision
    message: str
    status_code: int
    run_id: str | None = None  # the run the command started (start, calibrations, ...)

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
        result = self.result.as_dict()
        result.pop("run_id")  # a refused command started no run
        return {**super().as_dict(), **result}


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
    """503: the event queue is full or the journal cannot write (the message says which);
    retry after `retry_after` s."""

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
