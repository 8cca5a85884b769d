"""gluectl: drive and watch the glue cell from a shell or a script.

    gluectl state                        where the cell is, what it may do next
    gluectl start --workpiece demo       spray (202 → exit 0; refused → exit 3)
    gluectl wait IDLE --timeout 120      block until the cell is back in IDLE
    gluectl watch                        live view: progress bar and state timeline
    gluectl order start demo 20          make 20 good parts, one run after another
    gluectl settings set shift_hours=10  change a runtime setting; it stays over a restart
    gluectl line --broker mqtt://host:1883   every cell of a line, live from the broker
    gluectl --json history --limit 5     anything as JSON (--json before or after the command)
    gluectl --mqtt mqtt://broker:1883 --cell-id cell-1 start   the same command, signed, over MQTT

Global options go before the command: --url (env GLUE_CELL_URL, default
http://127.0.0.1:8000), --token (env GLUE_CELL_TOKEN, else <data dir>/admin.token),
--data-dir (env GLUE_APP_DATA_PATH, default ./data), --ca-file (env
GLUE_CELL_CA_FILE: the CA an https server's certificate must chain to), --json. With
--mqtt (env GLUE_MQTT_URL) the commands (start, pause, resume, cancel, estop, reset,
home, jog, calibrations, create-workpiece) go to --cell-id over the broker instead,
signed with the token (clients/client/mqtt_commands.py), and the answer is printed as
over HTTP; --mqtt-user, --mqtt-password (env GLUE_MQTT_PASSWORD, or
--mqtt-password-file), --mqtt-ca-file and --mqtt-prefix say how to reach the broker
(docs/cli.md).

Exit codes, stable for scripts (the reason is printed on stderr):

    0  accepted / ok
    1  an unexpected answer (e.g. a 500), never a documented outcome
    2  usage error: unknown option, bad argument (typer's)
    3  refused (409): the command is not allowed in the current state;
       `allowed` exits 3 when the answer is no
    4  unauthorized or forbidden (401/403): no valid token, or the role is too low
    5  unreachable: no connection, or no answer in time
    6  invalid request (422), or not found (404)
    7  busy (503): the event queue is full or the journal cannot write; retry shortly
    8  timeout in `wait`
    9  `wait`: the cell is in ERROR, which only a reset leaves (even if it was
       already there); --no-fail-on-error waits through it for someone's reset

With --json every command prints one JSON document on stdout, errors too
(`{"error": "Refused", "status_code": 409, "message": ...}`), usage errors
included (`{"error": "UsageError", ...}`, exit 2); `watch --json` prints one
message per line. `gluectl --version` prints the package's version.
"""

from __future__ import annotations

import asyncio
import json
import os
import ssl
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from importlib import metadata
from pathlib import Path
from typing import Annotated, Any, NoReturn, TypeVar

import httpx
import typer
from rich.console import Console, Group, RenderableType
from rich.live import Live
from rich.panel import Panel
from rich.progress_bar import ProgressBar
from rich.table import Table
from rich.text import Text

from clients.client import (
    CA_FILE_ENV,
    DATA_DIR_ENV,
    DEFAULT_URL,
    TOKEN_ENV,
    URL_ENV,
    AsyncCellClient,
    Busy,
    CellClient,
    CellError,
    CellFaulted,
    CommandResult,
    Forbidden,
    InvalidRequest,
    Refused,
    Unauthorized,
    Unreachable,
    WaitTimeout,
    normalize_state,
    normalize_url,
    resolve_token,
    trust,
)
from clients.client.mqtt_commands import MqttCellClient, MqttTarget
from clients.gluectl_format import key_values as _key_values
from clients.gluectl_format import value as _value
from clients.gluectl_format import when as _when
from clients.gluectl_report import report_table, reports_table
from clients.gluectl_settings import parse_assignments, settings_rows, settings_table
from clients.line_model import DEFAULT_PREFIX, LineModel
from clients.line_table import line_table
from clients.line_watch import Broker, LineUnreachable, LineWatcher

T = TypeVar("T")

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

PIPED_WIDTH = 160

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


app = typer.Typer(
    name="gluectl",
    help="Drive and watch the glue cell over its HTTP and WebSocket API.",
    epilog="\b\n" + EXIT_CODES_HELP,  # \b: click keeps the lines as written
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
    context_settings={"help_option_names": ["-h", "--help"]},
)


@dataclass(frozen=True)
class Options:
    """The global options, resolved once in the callback."""

    url: str
    token: str | None
    token_source: str
    json: bool
    timeout: float
    mqtt: MqttTarget | None = None  # commands go over this broker instead of HTTP
    ca_file: Path | None = None

    def client(self) -> CellClient:
        return CellClient(self.url, self.token, timeout=self.timeout, ca_file=self.ca_file)

    def command_client(self) -> CellClient | MqttCellClient:
        """Where commands go: the broker with --mqtt, else the HTTP API."""
        if self.mqtt is not None:
            return MqttCellClient(self.mqtt, self.token, timeout=self.timeout)
        return self.client()

    def async_client(self) -> AsyncCellClient:
        return AsyncCellClient(self.url, self.token, timeout=self.timeout, ca_file=self.ca_file)


JsonFlag = Annotated[
    bool, typer.Option("--json", help="Machine-readable output (same as the global --json).")
]


def package_version() -> str:
    """The installed distribution's version (pyproject.toml), or why it is unknown."""
    try:
        return metadata.version("glue-cell-server")
    except metadata.PackageNotFoundError:
        return "(not installed: run from a checkout)"


def _show_version(value: bool) -> None:
    if value:
        typer.echo(f"gluectl {package_version()}")
        raise typer.Exit(EXIT_OK)


@app.callback()
def main_options(
    ctx: typer.Context,
    url: Annotated[
        str, typer.Option("--url", envvar=URL_ENV, help="The cell server's base URL.")
    ] = DEFAULT_URL,
    token: Annotated[
        str | None,
        typer.Option(
            "--token",
            envvar=TOKEN_ENV,
            help="Bearer token; default: the data dir's admin.token.",
            show_default=False,
        ),
    ] = None,
    data_dir: Annotated[
        Path | None,
        typer.Option(
            "--data-dir",
            help=f"Where to find admin.token (default: ${DATA_DIR_ENV}, else ./data).",
            show_default=False,
        ),
    ] = None,
    ca_file: Annotated[
        Path | None,
        typer.Option(
            "--ca-file",
            envvar=CA_FILE_ENV,
            help="CA certificate (PEM) an https server's certificate must chain to "
            "(default: the public CAs).",
            show_default=False,
        ),
    ] = None,
    json_output: Annotated[
        bool, typer.Option("--json", help="Machine-readable output: one JSON document.")
    ] = False,
    timeout: Annotated[
        float, typer.Option("--http-timeout", min=0.1, help="Seconds to wait for each answer.")
    ] = 10.0,
    version: Annotated[
        bool,
        typer.Option(
            "--version", is_eager=True, callback=_show_version, help="Print the version and exit."
        ),
    ] = False,
    mqtt: Annotated[
        str | None,
        typer.Option(
            "--mqtt",
            envvar="GLUE_MQTT_URL",
            help="Send commands over this broker (mqtt://host:1883, mqtts://host:8883), signed.",
            show_default=False,
        ),
    ] = None,
    cell_id: Annotated[
        str | None,
        typer.Option(
            "--cell-id",
            envvar="GLUE_CELL_ID",
            help="The cell to command (--mqtt).",
            show_default=False,
        ),
    ] = None,
    mqtt_user: Annotated[
        str | None,
        typer.Option("--mqtt-user", envvar="GLUE_MQTT_USER", help="User name at the broker."),
    ] = None,
    mqtt_password: Annotated[
        str | None,
        typer.Option(
            "--mqtt-password",
            envvar="GLUE_MQTT_PASSWORD",
            help="Password at the broker (better: the env var or --mqtt-password-file).",
            show_default=False,
        ),
    ] = None,
    mqtt_password_file: Annotated[
        Path | None,
        typer.Option("--mqtt-password-file", help="A file whose first line is the password."),
    ] = None,
    mqtt_ca_file: Annotated[
        Path | None,
        typer.Option("--mqtt-ca-file", help="CA certificate (PEM) for an mqtts:// broker."),
    ] = None,
    mqtt_prefix: Annotated[
        str, typer.Option("--mqtt-prefix", help="The cell's topic prefix.")
    ] = DEFAULT_PREFIX,
) -> None:
    """Drive and watch the glue cell over its HTTP and WebSocket API."""
    try:
        url = str(httpx.URL(normalize_url(url)))
    except httpx.InvalidURL as exc:
        raise typer.BadParameter(str(exc), param_hint="--url") from None
    if ca_file is not None:  # read now: a wrong path is a usage error, not "unreachable"
        try:
            trust(ca_file)
        except (OSError, ssl.SSLError) as exc:
            reason = getattr(exc, "strerror", None) or str(exc)
            raise typer.BadParameter(f"{ca_file}: {reason}", param_hint="--ca-file") from None
    resolved = resolve_token(token, data_dir=data_dir)
    where = data_dir or f"${DATA_DIR_ENV} or ./data"
    if token:
        source = f"from --token or ${TOKEN_ENV}"
    elif resolved:
        source = f"from admin.token in {where}"
    else:
        source = f"none found (--token, ${TOKEN_ENV}, or admin.token in {where})"
    target = None
    if mqtt:
        target = _mqtt_target(
            mqtt, cell_id, mqtt_user, mqtt_password, mqtt_password_file, mqtt_ca_file, mqtt_prefix
        )
    ctx.obj = Options(url, resolved, source, json_output, timeout, target, ca_file)


def _mqtt_target(
    url: str,
    cell_id: str | None,
    user: str | None,
    password: str | None,
    password_file: Path | None,
    ca_file: Path | None,
    prefix: str,
) -> MqttTarget:
    """The broker and cell of --mqtt, checked before anything is sent."""
    if not cell_id:
        raise typer.BadParameter(
            "--mqtt needs --cell-id (or $GLUE_CELL_ID)", param_hint="--cell-id"
        )
    if password_file is not None:
        try:
            lines = password_file.read_text(encoding="utf-8").splitlines()
        except OSError as error:
            raise typer.BadParameter(str(error), param_hint="--mqtt-password-file") from None
        password = lines[0] if lines else ""
    target = MqttTarget(url, cell_id, prefix, user, password, ca_file)
    try:
        target.address()
    except ValueError as error:
        raise typer.BadParameter(str(error), param_hint="--mqtt") from None
    return target


# --- output ------------------------------------------------------------------------


def _options(ctx: typer.Context, json_flag: bool) -> Options:
    options: Options = ctx.obj
    return replace(options, json=True) if json_flag else options


def _stdout() -> Console:
    """Rich output; piped (a file, grep, less) tables take their natural width, not 80."""
    console = Console(highlight=False, soft_wrap=False)
    if not console.is_terminal and "COLUMNS" not in os.environ:
        console = Console(highlight=False, soft_wrap=False, width=PIPED_WIDTH)
    return console


def _print_json(data: Any) -> None:
    typer.echo(json.dumps(data, ensure_ascii=False, default=str))


def _fail(options: Options, error: CellError) -> NoReturn:
    """Report `error` (reason on stderr, JSON on stdout with --json) and exit with its code."""
    code = exit_code(error)
    if options.json:
        _print_json(error.as_dict())
    label = {
        EXIT_REFUSED: "refused",
        EXIT_AUTH: "unauthorized" if isinstance(error, Unauthorized) else "forbidden",
        EXIT_UNREACHABLE: "unreachable",
        EXIT_INVALID: "invalid request",
        EXIT_BUSY: "busy",
        EXIT_TIMEOUT: "timeout",
        EXIT_FAULTED: "fault",
    }.get(code, "error")
    reason = str(error).removeprefix(f"{label}: ")  # the server's 422 says it already
    typer.echo(f"gluectl: {label}: {reason}", err=True)
    if isinstance(error, Unauthorized):  # which token was it, if any?
        typer.echo(f"gluectl: token: {options.token_source}", err=True)
    if isinstance(error, Busy):
        typer.echo(f"gluectl: retry after {error.retry_after:g} s", err=True)
    raise typer.Exit(code)


def _call(options: Options, action: Callable[[CellClient], T]) -> T:
    if options.mqtt is not None:
        raise typer.BadParameter(
            "only commands go over MQTT; ask the cell's HTTP API (--url) for the rest",
            param_hint="--mqtt",
        )
    try:
        with options.client() as client:
            return action(client)
    except CellError as error:
        _fail(options, error)


def _command(ctx: typer.Context, json_flag: bool, action: Callable[[Any], CommandResult]) -> None:
    """Run a command (over HTTP, or signed over MQTT with --mqtt); print the decision.
    Refusals and errors exit through `_fail`."""
    options = _options(ctx, json_flag)
    try:
        with options.command_client() as client:
            result = action(client)
    except CellError as error:
        _fail(options, error)
    except ValueError as error:  # e.g. no token to sign with, or not an API token
        raise typer.BadParameter(str(error), param_hint="--token") from None
    if options.json:
        _print_json(result.as_dict())
    else:
        event = f"  (event {result.event_id})" if result.event_id else ""
        typer.echo(f"{result.message}{event}")


def _fault(fault: dict[str, Any] | None) -> str:
    if not fault:
        return "—"
    return f"{fault.get('code')}: {fault.get('message')} ({fault.get('recommended_action', '')})"


def _progress(progress: dict[str, Any] | None) -> str:
    if not progress or not progress.get("total"):
        return ""
    fraction = progress.get("fraction") or 0.0
    return f"waypoint {progress.get('waypoint')}/{progress['total']} ({fraction:.0%})"


def state_table(state: dict[str, Any]) -> Table:
    """GET /state as a key/value table."""
    operation = state.get("operation")
    running = "—"
    if operation:
        running = f"{operation.get('name')} (run {operation.get('run_id')})"
        progress = _progress(operation.get("progress"))
        running += f"  {progress}" if progress else ""
    rows = [
        ("state", str(state.get("state"))),
        ("previous", _value(state.get("previous_state"))),
        ("since", f"{_when(state.get('since'))}  ({_value(state.get('time_in_state'))} s)"),
        ("operation", running),
        ("error", _fault(state.get("error"))),
        ("stop reason", _fault(state.get("stop_reason"))),
        ("may do", ", ".join(state.get("available_commands") or []) or "—"),
    ]
    if state.get("operation_result"):
        rows.append(("last result", _value(state["operation_result"])))
    return _key_values("cell", rows)


def history_table(rows: list[dict[str, Any]]) -> Table:
    table = Table(title="transitions, newest first", title_justify="left")
    for column in ("time", "from", "to", "event", "event id", "in old (s)"):
        table.add_column(column, justify="right" if "(s)" in column else "left", overflow="fold")
    for row in rows:
        table.add_row(
            *(
                Text(v)
                for v in (
                    _when(row.get("time"), short=True),
                    _value(row.get("old_state")),
                    _value(row.get("new_state")),
                    _value(row.get("event")),
                    _value(row.get("event_id")),
                    _value(row.get("time_in_old_state")),
                )
            )
        )
    return table


def workpieces_table(rows: list[dict[str, Any]]) -> Table:
    table = Table(title="workpiece library", title_justify="left")
    for column in ("id", "name", "source", "outline points", "fill", "created"):
        table.add_column(column, overflow="fold")
    for row in rows:
        spray = row.get("spray") or {}
        table.add_row(
            *(
                Text(v)
                for v in (
                    _value(row.get("id")),
                    _value(row.get("name")),
                    _value(row.get("source")),
                    str(len(row.get("outline_mm") or [])),
                    _value(spray.get("fill")),
                    _when(row.get("created_at"), short=True),
                )
            )
        )
    return table


def _flatten(data: dict[str, Any], prefix: str = "") -> Iterator[tuple[str, Any]]:
    for key, value in data.items():
        if isinstance(value, dict):
            yield from _flatten(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value


def kpis_table(kpis: dict[str, Any]) -> Table:
    window = kpis.get("window") or {}
    title = f"KPIs {_when(window.get('start'))} → {_when(window.get('end'))}"
    rows = [(k, _value(v)) for k, v in _flatten(kpis) if not k.startswith("window.")]
    return _key_values(title, rows)


def maintenance_table(state: dict[str, Any]) -> Table:
    rows = [(f"counter {k}", _value(v)) for k, v in (state.get("counters") or {}).items()]
    for item in state.get("items") or ():
        rows.append((f"item {item['name']}", f"{item['status']} {item['percent']} %"))
    for key in ("pot_life", "glue_level"):
        rows.append((key.replace("_", " "), _value((state.get(key) or {}).get("status"))))
    return _key_values("maintenance", rows)


def health_table(health: dict[str, Any]) -> Table:
    table = Table(
        title=f"health: {health.get('status')} (state {health.get('state')})", title_justify="left"
    )
    for column in ("device", "connected", "last rtt ms", "last error"):
        table.add_column(column)
    for name, device in (health.get("devices") or {}).items():
        table.add_row(
            Text(name),
            Text(_value(device.get("connected"))),
            Text(_value(device.get("last_rtt_ms"))),
            Text(_value(device.get("last_error"))),
        )
    return table


def _show(options: Options, data: Any, render: Callable[[Any], RenderableType]) -> None:
    if options.json:
        _print_json(data)
    else:
        _stdout().print(render(data))


# --- commands ----------------------------------------------------------------------


@app.command()
def state(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """Show the state, the running operation and its progress, the fault if any."""
    options = _options(ctx, json_flag)
    _show(options, _call(options, lambda c: c.state()), state_table)


@app.command()
def start(
    ctx: typer.Context,
    workpiece: Annotated[
        str | None, typer.Option("--workpiece", help="Spray (or match only) this library id.")
    ] = None,
    contour_matching: Annotated[
        bool,
        typer.Option(
            "--contour-matching/--no-contour-matching",
            help="Find the part on the table and match it (default), or spray it as stored.",
        ),
    ] = True,
    json_flag: JsonFlag = False,
) -> None:
    """Start spraying (IDLE → EXECUTING_TRAJECTORY)."""
    _command(ctx, json_flag, lambda c: c.start(workpiece, contour_matching))


@app.command()
def pause(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """Stop the trajectory where it is, glue off; resume continues the same segment."""
    _command(ctx, json_flag, lambda c: c.pause())


@app.command()
def resume(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """Continue a paused trajectory from where it held."""
    _command(ctx, json_flag, lambda c: c.resume())


@app.command()
def cancel(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """Stop the running operation at once, glue off, back to IDLE."""
    _command(ctx, json_flag, lambda c: c.cancel())


@app.command()
def estop(
    ctx: typer.Context,
    reason: Annotated[
        str | None, typer.Option("--reason", help="Why, for the record (≤ 200 characters).")
    ] = None,
    json_flag: JsonFlag = False,
) -> None:
    """Software stop: valve closed, robot stopped, then ERROR. Not a safety function."""
    _command(ctx, json_flag, lambda c: c.estop(reason))


@app.command()
def reset(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """Leave ERROR for IDLE once every device answers (maintenance role)."""
    _command(ctx, json_flag, lambda c: c.reset())


@app.command()
def home(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """Send the robot to its safe position; the cell stays IDLE (maintenance role)."""
    _command(ctx, json_flag, lambda c: c.home())


@app.command()
def purge(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """Purge the glue line at the purge position; the cell stays IDLE (maintenance role)."""
    _command(ctx, json_flag, lambda c: c.purge())


@app.command()
def maintenance(
    ctx: typer.Context,
    done: Annotated[
        str | None, typer.Option("--done", help="mark this item done (maintenance role)")
    ] = None,
    refill: Annotated[
        bool, typer.Option("--refill", help="the glue reservoir was refilled (maintenance role)")
    ] = False,
    json_flag: JsonFlag = False,
) -> None:
    """Wear counters, the maintenance schedule, pot life and glue level; --done ITEM, --refill."""
    options = _options(ctx, json_flag)
    if done is not None:
        _call(options, lambda c: c.maintenance_done(done))
    if refill:
        _call(options, lambda c: c.glue_refill())
    _show(options, _call(options, lambda c: c.maintenance()), maintenance_table)


@app.command()
def jog(
    ctx: typer.Context,
    axis: Annotated[str, typer.Argument(help="x, y or z (robot base frame).")],
    distance_mm: Annotated[
        float, typer.Argument(help="The step in mm; a negative one after --: jog x -- -5.")
    ],
    json_flag: JsonFlag = False,
) -> None:
    """Move the robot one bounded step, in IDLE (maintenance role)."""
    _command(ctx, json_flag, lambda c: c.jog(axis, distance_mm))


def marker_table(layout: dict[str, Any]) -> Table:
    """GET /calibration/markers: in force and draft, marker by marker."""
    position = (layout.get("robot") or {}).get("position")
    where = _value(position[:3] if isinstance(position, list) else None)
    table = Table(title=f"markers ({layout.get('source')}); robot at {where}", title_justify="left")
    for column in ("marker", "in force (mm)", "draft (mm)", "how"):
        table.add_column(column, overflow="fold")
    drafts = layout.get("draft") or []
    for i, (x, y) in enumerate(layout.get("in_force") or []):
        draft = drafts[i] if i < len(drafts) else None
        typed = f"{_value(draft['x_mm'])}, {_value(draft['y_mm'])}" if draft else "—"
        how = draft["how"] if draft else "missing"
        table.add_row(*(Text(v) for v in (str(i), f"{_value(x)}, {_value(y)}", typed, how)))
    return table


marker_app = typer.Typer(help="The marker layout robot calibration uses, taught with the robot.")
app.add_typer(marker_app, name="marker")


@marker_app.command("list")
def marker_list(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """The layout in force and the draft being taught."""
    options = _options(ctx, json_flag)
    _show(options, _call(options, lambda c: c.markers()), marker_table)


@marker_app.command("teach")
def marker_teach(
    ctx: typer.Context,
    marker: Annotated[int, typer.Argument(min=0, max=8, help="ArUco marker id, 0-8.")],
    json_flag: JsonFlag = False,
) -> None:
    """Record the tool's current x, y as marker N in the draft (maintenance role)."""
    options = _options(ctx, json_flag)
    _show(options, _call(options, lambda c: c.teach_marker(marker)), marker_table)


@marker_app.command("apply")
def marker_apply(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """Put the draft in force once all nine pass the layout check (maintenance role)."""
    options = _options(ctx, json_flag)
    _show(options, _call(options, lambda c: c.apply_markers()), marker_table)


def order_table(order: dict[str, Any]) -> Table:
    rows = [
        ("order", order["order_id"]),
        ("workpiece", order["workpiece_id"]),
        ("state", order["state"]),
        ("good", f"{order['good']} of {order['quantity']}"),
        (
            "defective",
            f"{order['defective']} ({order['defects_in_row']} in a row, "
            f"limit {order['defect_limit']})",
        ),
        ("reason", _value(order.get("reason"))),
        ("created", f"{_when(order['created_at'])} by {order['created_by']}"),
    ]
    return _key_values("order", rows)


def orders_table(listing: dict[str, Any]) -> Table:
    table = Table(title="production orders", title_justify="left")
    for column in ("order", "workpiece", "state", "good", "defective", "reason"):
        table.add_column(column, overflow="fold")
    for o in listing["orders"]:
        marker = " *" if o["order_id"] == listing.get("active") else ""
        table.add_row(
            *(
                Text(v)
                for v in (
                    o["order_id"] + marker,
                    o["workpiece_id"],
                    o["state"],
                    f"{o['good']}/{o['quantity']}",
                    str(o["defective"]),
                    _value(o.get("reason")),
                )
            )
        )
    return table


def order_report_table(report: dict[str, Any]) -> Table:
    order = report["order"]
    table = Table(
        title=f"order {order['order_id']}: {order['good']}/{order['quantity']} good, "
        f"{order['defective']} defective ({order['state']})",
        title_justify="left",
    )
    for column in ("part", "run", "ended", "verdict", "precision mm", "glue ml", "reasons"):
        table.add_column(column, overflow="fold")
    for p in report["parts"]:
        table.add_row(
            *(
                Text(v)
                for v in (
                    str(p["part"]),
                    p["run_id"],
                    _when(p["ended_at"], short=True),
                    p["verdict"],
                    _value(p.get("precision_mean_mm")),
                    _value(p.get("glue_ml")),
                    "; ".join(p["reasons"]),
                )
            )
        )
    return table


order_app = typer.Typer(help="Production orders: N good parts of a workpiece, run one by one.")
app.add_typer(order_app, name="order")
OrderIdArg = Annotated[str, typer.Argument(help="The order's id (gluectl order list).")]


def _order_answer(answer: dict[str, Any]) -> dict[str, Any]:
    return answer.get("order", answer)


@order_app.command("start")
def order_start(
    ctx: typer.Context,
    workpiece: Annotated[str, typer.Argument(help="The library workpiece to make.")],
    quantity: Annotated[int, typer.Argument(min=1, help="How many good parts.")],
    json_flag: JsonFlag = False,
) -> None:
    """Make QUANTITY good parts of WORKPIECE: runs at once, or queues (operator role)."""
    options = _options(ctx, json_flag)
    answer = _call(options, lambda c: c.create_order(workpiece, quantity))
    _show(options, answer, lambda a: order_table(_order_answer(a)))


@order_app.command("show")
def order_show(ctx: typer.Context, order_id: OrderIdArg, json_flag: JsonFlag = False) -> None:
    """One order: state, why, good and defective parts."""
    options = _options(ctx, json_flag)
    _show(options, _call(options, lambda c: c.order(order_id)), order_table)


@order_app.command("list")
def order_list(
    ctx: typer.Context,
    state: Annotated[
        str | None, typer.Option("--state", help="queued, running, held, completed, closed")
    ] = None,
    json_flag: JsonFlag = False,
) -> None:
    """The orders, newest first (* marks the active one)."""
    options = _options(ctx, json_flag)
    _show(options, _call(options, lambda c: c.orders(state)), orders_table)


@order_app.command("close")
def order_close(ctx: typer.Context, order_id: OrderIdArg, json_flag: JsonFlag = False) -> None:
    """End an order before its quantity; a run under way goes on (operator role)."""
    options = _options(ctx, json_flag)
    _show(options, _call(options, lambda c: c.close_order(order_id)), order_table)


@order_app.command("resume")
def order_resume(ctx: typer.Context, order_id: OrderIdArg, json_flag: JsonFlag = False) -> None:
    """Continue a held order; the cell must be IDLE (reset it first) (operator role)."""
    options = _options(ctx, json_flag)
    answer = _call(options, lambda c: c.resume_order(order_id))
    _show(options, answer, lambda a: order_table(_order_answer(a)))


@order_app.command("report")
def order_report(
    ctx: typer.Context,
    order_id: OrderIdArg,
    csv_flag: Annotated[bool, typer.Option("--csv", help="The report as CSV on stdout.")] = False,
    json_flag: JsonFlag = False,
) -> None:
    """Every part of an order: run, time, verdict, precision, glue used, reasons."""
    options = _options(ctx, json_flag)
    if csv_flag:
        typer.echo(_call(options, lambda c: c.order_report_csv(order_id)), nl=False)
        return
    _show(options, _call(options, lambda c: c.order_report(order_id)), order_report_table)


@app.command("calibrate-robot")
def calibrate_robot(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """Fit the image → robot map from ArUco markers 0-8 (maintenance role)."""
    _command(ctx, json_flag, lambda c: c.calibrate_robot())


@app.command("calibrate-camera")
def calibrate_camera(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """Calibrate the camera's intrinsics from chessboard views (maintenance role)."""
    _command(ctx, json_flag, lambda c: c.calibrate_camera())


@app.command("create-workpiece")
def create_workpiece(
    ctx: typer.Context,
    name: Annotated[str | None, typer.Option("--name", help="The workpiece's name.")] = None,
    workpiece_id: Annotated[
        str | None, typer.Option("--id", help="Store under this id (default: the next wp-NNNN).")
    ] = None,
    if_new: Annotated[
        bool,
        typer.Option(
            "--if-new",
            help="Store it only if it matches no stored part; `gluectl state` then shows "
            "which part it matches and how well (operation_result.similar).",
        ),
    ] = False,
    json_flag: JsonFlag = False,
) -> None:
    """Capture the largest part on the table into the library."""
    _command(ctx, json_flag, lambda c: c.create_workpiece(name, workpiece_id, if_new))


@app.command()
def workpieces(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """List the workpiece library."""
    options = _options(ctx, json_flag)
    _show(options, _call(options, lambda c: c.workpieces()), workpieces_table)


@app.command()
def history(
    ctx: typer.Context,
    limit: Annotated[
        int, typer.Option("--limit", min=1, max=10_000, help="How many transitions.")
    ] = 20,
    json_flag: JsonFlag = False,
) -> None:
    """The latest state transitions, newest first."""
    options = _options(ctx, json_flag)
    _show(options, _call(options, lambda c: c.history(limit)), history_table)


@app.command()
def kpis(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """The current shift's KPIs and OEE."""
    options = _options(ctx, json_flag)
    _show(options, _call(options, lambda c: c.kpis()), kpis_table)


report_app = typer.Typer(help="Shift and daily reports: parts, OEE, stop reasons, alerts.")
app.add_typer(report_app, name="report")
HtmlOption = Annotated[
    Path | None,
    typer.Option("--html", help="Write the printable page (with its charts) to this file."),
]
IdOption = Annotated[
    int | None,
    typer.Option("--id", min=1, help="This report (gluectl report list), not the latest."),
]


def _report(options: Options, period: str, report_id: int | None, html: Path | None) -> None:
    if report_id is None:
        latest = _call(options, lambda c: c.reports(period, 1))
        if not latest:
            typer.echo(
                f"gluectl: no {period} report yet: one is made at each {period}'s end", err=True
            )
            raise typer.Exit(EXIT_REFUSED)
        report_id = int(latest[0]["id"])
    chosen = report_id
    if html is not None:
        html.write_text(_call(options, lambda c: c.report_html(chosen)), encoding="utf-8")
        _stdout().print(f"wrote {html}")
        return
    _show(options, _call(options, lambda c: c.report(chosen)), report_table)


@report_app.command("shift")
def report_shift(
    ctx: typer.Context, id_: IdOption = None, html: HtmlOption = None, json_flag: JsonFlag = False
) -> None:
    """The latest shift's report (or --id's): parts, OEE, stop reasons, alerts."""
    _report(_options(ctx, json_flag), "shift", id_, html)


@report_app.command("day")
def report_day(
    ctx: typer.Context, id_: IdOption = None, html: HtmlOption = None, json_flag: JsonFlag = False
) -> None:
    """The latest production day's report (or --id's)."""
    _report(_options(ctx, json_flag), "day", id_, html)


@report_app.command("list")
def report_list(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """The reports kept, newest first."""
    options = _options(ctx, json_flag)
    _show(options, _call(options, lambda c: c.reports()), reports_table)


@app.command()
def health(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """Each device's link, last round trip and last error (needs no token)."""
    options = _options(ctx, json_flag)
    _show(options, _call(options, lambda c: c.health()), health_table)


settings_app = typer.Typer(help="The settings in force, and the runtime ones changed (admin).")
app.add_typer(settings_app, name="settings")


@settings_app.command("get")
def settings_get(
    ctx: typer.Context,
    names: Annotated[
        list[str] | None, typer.Argument(help="Settings to show (all if none).")
    ] = None,
    json_flag: JsonFlag = False,
) -> None:
    """Each setting's value, where it comes from, and whether a change applies at once."""
    options = _options(ctx, json_flag)
    data = _call(options, lambda c: c.settings())
    try:
        rows = settings_rows(data, names or None)
    except KeyError as missing:
        raise typer.BadParameter(
            f"{missing.args[0]} names no setting", param_hint="NAMES"
        ) from None
    _show(options, rows, settings_table)


@settings_app.command("set")
def settings_set(
    ctx: typer.Context,
    assignments: Annotated[list[str], typer.Argument(help="NAME=VALUE, e.g. shift_hours=10.")],
    json_flag: JsonFlag = False,
) -> None:
    """Change runtime settings at once; they are saved and stay over a restart."""
    options = _options(ctx, json_flag)
    try:
        body = parse_assignments(assignments)
    except ValueError as error:
        raise typer.BadParameter(str(error), param_hint="NAME=VALUE") from None
    answer = _call(options, lambda c: c.change_settings(**body))
    if options.json:
        _print_json(answer)
        return
    changed = answer.get("changed") or {}
    for name, change in changed.items():
        typer.echo(f"{name}: {_value(change['old'])} -> {_value(change['new'])} (saved)")
    if not changed:
        typer.echo("nothing changed: each value was in force already")


@app.command()
def allowed(
    ctx: typer.Context,
    command: Annotated[str, typer.Argument(help="A command name, e.g. start or calibrate-robot.")],
    json_flag: JsonFlag = False,
) -> None:
    """Would COMMAND be accepted now? Exit 0 if yes, 3 if not; the reason either way."""
    options = _options(ctx, json_flag)
    answer = _call(options, lambda c: c.allowed(command))
    if options.json:
        _print_json(answer)
    else:
        typer.echo(answer.get("reason", ""))
    if not answer.get("allowed"):
        raise typer.Exit(EXIT_REFUSED)


@app.command()
def wait(
    ctx: typer.Context,
    state: Annotated[
        str, typer.Argument(metavar="STATE", help="e.g. IDLE, PAUSED, ERROR (any case).")
    ],
    timeout: Annotated[
        float, typer.Option("--timeout", min=0, help="Give up after this many seconds (exit 8).")
    ] = 60.0,
    interval: Annotated[
        float, typer.Option("--interval", min=0.01, help="Seconds between polls of /state.")
    ] = 0.1,
    fail_on_error: Annotated[
        bool,
        typer.Option(
            "--fail-on-error/--no-fail-on-error",
            help="Stop at once (exit 9) when the cell is in ERROR (unless waiting for ERROR).",
        ),
    ] = True,
    json_flag: JsonFlag = False,
) -> None:
    """Block until the cell is in STATE (polls GET /state); exit 8 on timeout, 9 in ERROR."""
    options = _options(ctx, json_flag)
    try:
        wanted = normalize_state(state)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="STATE") from None
    fail_on = ("ERROR",) if fail_on_error else ()
    reached = _call(
        options,
        lambda c: c.wait_for_state(wanted, timeout, poll_interval=interval, fail_on=fail_on),
    )
    if options.json:
        _print_json(reached)
    else:
        typer.echo(reached["state"])


# --- watch -------------------------------------------------------------------------


class WatchView:
    """What `watch` shows, built from /ws messages: state, progress bar, timeline."""

    def __init__(self, url: str, timeline: int = 12) -> None:
        self.url = url
        self.state = "?"
        self.since: float | None = None
        self.operation: dict[str, Any] | None = None
        self.progress: dict[str, Any] | None = None
        self.fault: dict[str, Any] | None = None
        self.timeline: deque[dict[str, Any]] = deque(maxlen=timeline)
        self.notes: deque[str] = deque(maxlen=3)
        self.seq: int | None = None
        self.received = 0

    def update(self, message: dict[str, Any]) -> None:
        self.received += 1
        self.seq = message.get("seq", self.seq)
        kind = message.get("type")
        if kind == "snapshot":
            self._take_snapshot(message)
            if _replaying(message):
                # The transitions that went by follow, and the timeline takes them as
                # they come: the snapshot's history would show them twice.
                self.notes.append(
                    f"reconnected: {message.get('replayed')} message(s) replayed, none missed"
                )
                return
            self.timeline.clear()
            self.timeline.extend(message.get("history") or [])
            if message.get("resumed"):
                restarted = " (the server restarted)" if message.get("restarted") else ""
                self.notes.append(
                    f"reconnected{restarted}: missed {message.get('missed')} message(s); resynced"
                )
        elif kind == "state_changed":
            self.timeline.append(message)
            self._take_snapshot(message.get("snapshot") or {"state": message.get("new_state")})
        elif kind == "progress":
            # The transition into an operation comes before the operation exists, so
            # the first progress message is what names it.
            operation = self.operation or {}
            if operation.get("run_id") != message.get("run_id"):
                self.operation = {"name": message.get("operation"), "run_id": message.get("run_id")}
            self.progress = message
        elif kind == "error":
            self.fault = self.fault or message  # the first-out fault stays on show
        elif kind == "alert":
            self.notes.append(f"alert: {message.get('message', message)}")

    def _take_snapshot(self, snapshot: dict[str, Any]) -> None:
        self.state = str(snapshot.get("state", self.state))
        self.since = snapshot.get("since", self.since)
        self.operation = snapshot.get("operation")
        progress = (self.operation or {}).get("progress")
        self.progress = progress if self.operation else None
        # The server's `error` is the latest fault ever (history); the line shows why the
        # cell is stopped, so only in ERROR, and the first-out fault as the dashboard does.
        in_error = self.state == "ERROR"
        self.fault = (snapshot.get("stop_reason") or snapshot.get("error")) if in_error else None

    def render(self) -> RenderableType:
        header = Text.assemble(
            ("state ", "dim"),
            (self.state, "bold red" if self.state == "ERROR" else "bold green"),
            (f"   since {_when(self.since)}   seq {_value(self.seq)}   {self.url}", "dim"),
        )
        parts: list[RenderableType] = [header]
        if self.operation:
            progress = self.progress or {}
            total = float(progress.get("total") or 1)
            done = float(progress.get("waypoint") or 0)
            bar = Table.grid(padding=(0, 1))
            bar.add_row(
                Text(f"{self.operation.get('name')}"),
                ProgressBar(total=total, completed=done, width=40),
                Text(_progress(progress) or "starting"),
            )
            parts.append(bar)
        if self.fault and self.state == "ERROR":
            parts.append(Text(f"fault {_fault(self.fault)}", style="red"))
        parts.extend(Text(note, style="yellow") for note in self.notes)
        timeline = Table(title="timeline", title_justify="left", expand=False)
        for column in ("time", "from", "to", "event"):
            timeline.add_column(column)
        for row in self.timeline:
            timeline.add_row(
                Text(_when(row.get("timestamp", row.get("time")))),
                Text(_value(row.get("old_state"))),
                Text(_value(row.get("new_state"))),
                Text(_value(row.get("event"))),
            )
        parts.append(timeline)
        return Panel(Group(*parts), title="glue cell", subtitle="Ctrl-C to quit")


def _replaying(message: dict[str, Any]) -> bool:
    """A resumed snapshot after which the server replays everything that went by."""
    return bool(message.get("resumed")) and "replayed" in message and message.get("missed") == 0


def message_line(message: dict[str, Any]) -> str:
    """One line per message, for `watch` when stdout is not a terminal."""
    kind = message.get("type")
    when = message.get("time", time.time())  # a snapshot has no time of its own: now
    prefix = f"{_when(when)}  seq {message.get('seq')}  {kind}"
    if kind == "snapshot":
        line = f"{prefix}  state {message.get('state')}"
        if _replaying(message):
            line += f"  (resumed, {message.get('replayed')} replayed, missed 0)"
        elif message.get("resumed"):
            restarted = " after a server restart" if message.get("restarted") else ""
            line += f"  (resumed{restarted}, missed {message.get('missed')})"
        return line
    if kind == "state_changed":
        return (
            f"{prefix}  {message.get('old_state')} → {message.get('new_state')}"
            f"  ({message.get('event')}, {message.get('event_id')})"
        )
    if kind == "progress":
        return f"{prefix}  {message.get('operation')}  {_progress(message)}".rstrip()
    if kind == "error":
        return f"{prefix}  {message.get('code')}: {message.get('message')}"
    return f"{prefix}  {json.dumps(message, ensure_ascii=False)}"


async def _watch(options: Options, count: int | None, types: list[str] | None) -> None:
    console = _stdout()
    live_view = not options.json and console.is_terminal
    view = WatchView(options.url)
    received = 0
    async with options.async_client() as client:
        stream = client.messages(types)
        async with stream:
            live = Live(view.render(), console=console, auto_refresh=False) if live_view else None
            if live:
                live.start()
            try:
                async for message in stream:
                    received += 1
                    if live:
                        view.update(message)
                        live.update(view.render(), refresh=True)
                    elif options.json:
                        _print_json(message)
                    else:
                        typer.echo(message_line(message))
                    sys.stdout.flush()
                    if count is not None and received >= count:
                        break
            finally:
                if live:
                    live.stop()


@app.command()
def watch(
    ctx: typer.Context,
    count: Annotated[
        int | None,
        typer.Option("--count", min=1, help="Exit after N messages (the snapshot counts)."),
    ] = None,
    types: Annotated[
        list[str] | None,
        typer.Option(
            "--type", help="Only these message types (repeatable): state_changed, progress, ..."
        ),
    ] = None,
    json_flag: JsonFlag = False,
) -> None:
    """Live view over /ws: progress bar and state timeline; reconnects by itself.

    On a terminal it redraws in place; piped, it prints one line per message
    (with --json, one JSON message per line). Ctrl-C quits.
    """
    options = _options(ctx, json_flag)
    try:
        asyncio.run(_watch(options, count, types))
    except CellError as error:
        _fail(options, error)
    except KeyboardInterrupt:
        raise typer.Exit(EXIT_OK) from None


def _line_show(options: Options, console: Console, model: LineModel, broker: Broker) -> None:
    if options.json:
        _print_json(model.as_json())
    else:
        console.print(line_table(model, str(broker)))
    sys.stdout.flush()


@app.command()
def line(
    ctx: typer.Context,
    broker_url: Annotated[
        str,
        typer.Option("--broker", envvar="GLUE_LINE_BROKER", help="The line's MQTT broker."),
    ] = "mqtt://127.0.0.1:1883",
    prefix: Annotated[
        str, typer.Option("--prefix", help="The cells' topic prefix (their mqtt_prefix).")
    ] = DEFAULT_PREFIX,
    once: Annotated[
        bool, typer.Option("--once", help="Print the line as the broker holds it now, and exit.")
    ] = False,
    json_flag: JsonFlag = False,
) -> None:
    """Every cell of a line from its MQTT broker: online/offline, state, stop reason,
    progress, OEE. Live (redrawn on a terminal, one table or JSON document per change
    when piped) until Ctrl-C. For scripts: --once --json. Exit 5 if the broker is
    unreachable.
    """
    options = _options(ctx, json_flag)
    try:
        broker = Broker.parse(broker_url)
    except ValueError as error:
        raise typer.BadParameter(str(error), param_hint="--broker") from None
    console = _stdout()
    watcher = LineWatcher(broker, prefix)
    try:
        watcher.connect(options.timeout)
        try:
            model = watcher.snapshot(options.timeout)
            if once:
                _line_show(options, console, model, broker)
                return
            _line_follow(options, console, watcher)
        finally:
            watcher.close()
    except LineUnreachable as error:
        _fail(options, Unreachable(str(error)))
    except KeyboardInterrupt:
        raise typer.Exit(EXIT_OK) from None


def _line_follow(options: Options, console: Console, watcher: LineWatcher) -> None:
    """Until Ctrl-C: redraw in place on a terminal, else print each new picture."""
    stop = threading.Event()
    if options.json or not console.is_terminal:
        _line_show(options, console, watcher.model, watcher.broker)
        watcher.follow(lambda m: _line_show(options, console, m, watcher.broker), stop)
        return
    with Live(line_table(watcher.model, str(watcher.broker)), console=console) as live:
        watcher.follow(lambda m: live.update(line_table(m, str(watcher.broker))), stop)


def _wants_json(args: list[str]) -> bool:
    """Whether --json is among the options (before a `--`), wherever the command is."""
    return "--json" in (args[: args.index("--")] if "--" in args else args)


def main(argv: list[str] | None = None) -> None:
    """Console entry point (`gluectl`, `python -m clients.gluectl`).

    With --json even a usage error (unknown option, bad value, missing argument)
    is one JSON document on stdout, like every other error, so a script parses
    one thing whatever went wrong. It is caught here, around the whole app, so
    every subcommand, present or added later, answers the same way.
    """
    args = sys.argv[1:] if argv is None else argv
    if not _wants_json(args):
        app(args=args, prog_name="gluectl")
        return
    try:
        code = app(args=args, prog_name="gluectl", standalone_mode=False)
    except typer.TyperException as error:  # click's UsageError and its kind
        message = error.format_message()
        _print_json({"error": "UsageError", "status_code": None, "message": message})
        typer.echo(f"gluectl: usage error: {message}", err=True)
        sys.exit(EXIT_USAGE if error.exit_code == EXIT_USAGE else EXIT_ERROR)
    except typer.Abort:
        sys.exit(EXIT_ERROR)
    sys.exit(code if isinstance(code, int) else EXIT_OK)


if __name__ == "__main__":
    main()
