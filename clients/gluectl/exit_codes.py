"""gluectl's exit codes, stable for scripts, and which client error exits with which.

The table is documented in the package's docstring (`clients/gluectl/__init__.py`)
and in `gluectl --help`'s epilog (`EXIT_CODES_HELP`).
"""

from __future__ import annotations

from clients.client import (
    Busy,
    CellError,
    CellFaulted,
    Forbidden,
    InvalidRequest,
    Refused,
    Unauthorized,
    Unreachable,
    WaitTimeout,
)

EXIT_OK = 0
EXIT_ERROR = 1
EXIT_USAGE = 2
EXIT_REFUSED = 3
EXIT_AUTH = 4
EXIT_UNREACHABLE = 5
EXIT_INVALID = 6
EXIT_BUSY = 7
EXIT_TIMEOUT = 8
EXIT_FAULTED = 9


EXIT_CODES_HELP = """\
Exit codes (the reason goes to stderr):
  0 ok · 1 unexpected answer · 2 usage error · 3 refused (409)
  4 unauthorized or forbidden (401/403) · 5 unreachable
  6 invalid request (422) or not found (404) · 7 busy (503)
  8 timeout in `wait` · 9 `wait` found the cell in ERROR"""


def exit_code(error: CellError) -> int:
    """The documented exit code of each client error (see the module docstring)."""
    codes: tuple[tuple[type[CellError], int], ...] = (
        (Refused, EXIT_REFUSED),
        (Unauthorized, EXIT_AUTH),
        (Forbidden, EXIT_AUTH),
        (Unreachable, EXIT_UNREACHABLE),
        (InvalidRequest, EXIT_INVALID),
        (Busy, EXIT_BUSY),
        (WaitTimeout, EXIT_TIMEOUT),
        (CellFaulted, EXIT_FAULTED),
    )
    for kind, code in codes:
        if isinstance(error, kind):
            return code
    return EXIT_ERROR
