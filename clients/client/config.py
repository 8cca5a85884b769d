"""Where the clients connect and with which token; the names the server uses.

Plain functions and constants, no I/O but reading the admin token file, shared
by both clients and by `gluectl`.
"""

from __future__ import annotations

import os
import ssl
from pathlib import Path

DEFAULT_URL = "http://127.0.0.1:8000"
URL_ENV = "GLUE_CELL_URL"
TOKEN_ENV = "GLUE_CELL_TOKEN"
CA_FILE_ENV = "GLUE_CELL_CA_FILE"
DATA_DIR_ENV = "GLUE_APP_DATA_PATH"  # the server's own data directory setting
DEFAULT_DATA_DIR = "data"
ADMIN_TOKEN_FILE = "admin.token"

# The machine's states, as the server names them (server/core/machine/transitions.py).
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
# The operator's commands, as the server names them (COMMANDS in the same file):
# each is POST /<name>, and a method of both clients (`-` read as `_`).
COMMANDS = (
    "start",
    "calibrate-robot",
    "calibrate-camera",
    "create-workpiece",
    "pause",
    "resume",
    "cancel",
    "estop",
    "reset",
    "home",
    "jog",
    "purge",
)
USER_AGENT = "glue-cell-client/0.1"
# Seconds an idle kept-alive connection is kept for the next request. The server closes one
# idle for its http_keepalive_timeout (5 s by default): a request sent just as it does gets
# no answer, and a command cannot be sent again (the server may have taken it). So a
# connection is let go well before the server would. Give the clients a shorter one
# (`keepalive_expiry`) for a server whose timeout is below twice this.
KEEPALIVE_EXPIRY_S = 2.0
WS_MAX_MESSAGE_BYTES = 16 * 2**20


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


def trust(ca_file: str | os.PathLike[str] | None) -> ssl.SSLContext | None:
    """How https and wss check the server: only the CA certificates (PEM) in `ca_file`,
    or None for the libraries' default (the publicly trusted CAs).

    A plant's cell has a certificate from the plant's own CA, which no default store
    holds; trusting that CA alone is what `curl --cacert` does. Raises OSError when the
    file cannot be read and ssl.SSLError when it holds no certificate.
    """
    if ca_file is None:
        return None
    return ssl.create_default_context(cafile=os.fspath(ca_file))


def default_headers(token: str | None) -> dict[str, str]:
    """The headers of every request: who is asking, and with which token."""
    headers = {"User-Agent": USER_AGENT}
    if token:
        headers["Authorization"] = f"Bearer {token}"
    return headers
