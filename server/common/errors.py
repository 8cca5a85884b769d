"""Every error the cell server raises on purpose, under one root.

Errors are split by who is at fault, so the HTTP layer can map them without
guessing: a request the current state forbids (the caller's timing), a device
that misbehaves (the cell's hardware), an operation that could not finish (the
work itself). Each message says what failed, where, and what to do next,
because the reader is often a technician standing at the cell.
"""

from __future__ import annotations

from typing import Any


class CellError(Exception):
    """Root of every deliberate error in the cell server."""


class ConfigurationError(CellError, ValueError):
    """A file or setting the server reads at start-up is invalid: the server does not start.

    The message is one line naming the file, the entry and the field, because it is
    all a technician sees when the service will not come up. A ValueError too, so
    a caller that catches ValueError around loading catches it.
    """


# --- the state machine -----------------------------------------------------


class TransitionNotAllowed(CellError):
    """The event has no transition from the current state; the state is unchanged."""

    def __init__(self, event: str, state: str, message: str | None = None) -> None:
        self.event = event
        self.state = state
        super().__init__(message or f"{event} is not allowed in {state}")


class GuardRefused(TransitionNotAllowed):
    """The transition exists but its condition does not hold (e.g. a fault is still active)."""


class EventQueueFull(CellError):
    """The event queue is at event_queue_size; the request was refused, not dropped."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        super().__init__(f"event queue is full ({capacity} events waiting); retry shortly")


class WorkerStopped(CellError):
    """The worker shut down before deciding on the event; nothing was changed."""


# --- storage ---------------------------------------------------------------


class JournalUnavailable(CellError):
    """The journal cannot write (a full disk, most often): the request was refused,
    nothing was changed. Every change must be on record before it is made."""

    def __init__(self, problem: str) -> None:
        self.problem = problem
        super().__init__(
            f"the journal cannot write ({problem}): nothing was changed; free space under "
            "the data directory, then try again"
        )


class ChangeNotSaved(CellError):
    """A change could not be written to its file (no space, most often); it was not applied.

    `status` is the HTTP answer: 507 when the disk had no room, 503 otherwise.
    """

    def __init__(self, what: str, problem: str, status: int = 507) -> None:
        self.what = what
        self.problem = problem
        self.status = status
        super().__init__(
            f"{what} could not be saved ({problem}): nothing was changed; free space under "
            "the data directory, then try again"
        )


# --- devices ---------------------------------------------------------------


class DeviceError(CellError):
    """A device failed to do what it was asked. `device` is robot, glue or camera."""

    def __init__(self, device: str, message: str) -> None:
        self.device = device
        super().__init__(f"{device}: {message}")


class DeviceTimeout(DeviceError):
    """A device did not answer within its configured timeout."""


class DeviceDisconnected(DeviceError):
    """The link to a device is down (refused, reset, or closed by the peer)."""


class RobotCommandError(DeviceError):
    """The robot controller answered a command with a JSON-RPC error."""

    def __init__(self, code: int, message: str, method: str = "") -> None:
        self.code = code
        self.method = method
        where = f"{method} " if method else ""
        super().__init__("robot", f"{where}refused (JSON-RPC error {code}): {message}")


# --- operations ------------------------------------------------------------


class OperationError(CellError):
    """An operation could not finish. `code` is a stable identifier for logs and KPIs.

    `recoverable` marks failures worth an automatic retry (a marker not found
    in one frame) as opposed to ones that need a person (workspace violation).
    """

    def __init__(self, code: str, message: str, *, recoverable: bool = False) -> None:
        self.code = code
        self.recoverable = recoverable
        super().__init__(message)

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickled whole: raised in the image process, it reaches the operation as it was."""
        return (self.__class__, (self.code, str(self)), self.__dict__)
