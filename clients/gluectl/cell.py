"""gluectl's commands of the cell's state machine: where the cell is (`state`, `history`,
`allowed`, `wait`) and what moves it (`start`, `pause`, `resume`, `cancel`, `estop`,
`reset`, `home`, `purge`, `jog`).
"""

from __future__ import annotations

from typing import Annotated, Any

import typer
from rich.table import Table
from rich.text import Text

from clients.client import normalize_state
from clients.gluectl.calls import call, command, options_for, print_json, show
from clients.gluectl.exit_codes import EXIT_REFUSED
from clients.gluectl.format import fault_line, progress_line
from clients.gluectl.format import key_values as _key_values
from clients.gluectl.format import value as _value
from clients.gluectl.format import when as _when
from clients.gluectl.options import JsonFlag


def state_table(state: dict[str, Any]) -> Table:
    """GET /state as a key/value table."""
    operation = state.get("operation")
    running = "—"
    if operation:
        running = f"{operation.get('name')} (run {operation.get('run_id')})"
        progress = progress_line(operation.get("progress"))
        running += f"  {progress}" if progress else ""
    rows = [
        ("state", str(state.get("state"))),
        ("previous", _value(state.get("previous_state"))),
        ("since", f"{_when(state.get('since'))}  ({_value(state.get('time_in_state'))} s)"),
        ("operation", running),
        ("error", fault_line(state.get("error"))),
        ("stop reason", fault_line(state.get("stop_reason"))),
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


def state(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """Show the state, the running operation and its progress, the fault if any."""
    options = options_for(ctx, json_flag)
    show(options, call(options, lambda c: c.state()), state_table)


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
    command(ctx, json_flag, lambda c: c.start(workpiece, contour_matching))


def pause(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """Stop the trajectory where it is, glue off; resume continues the same segment."""
    command(ctx, json_flag, lambda c: c.pause())


def resume(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """Continue a paused trajectory from where it held."""
    command(ctx, json_flag, lambda c: c.resume())


def cancel(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """Stop the running operation at once, glue off, back to IDLE."""
    command(ctx, json_flag, lambda c: c.cancel())


def estop(
    ctx: typer.Context,
    reason: Annotated[
        str | None, typer.Option("--reason", help="Why, for the record (≤ 200 characters).")
    ] = None,
    json_flag: JsonFlag = False,
) -> None:
    """Software stop: valve closed, robot stopped, then ERROR. Not a safety function."""
    command(ctx, json_flag, lambda c: c.estop(reason))


def reset(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """Leave ERROR for IDLE once every device answers (maintenance role)."""
    command(ctx, json_flag, lambda c: c.reset())


def home(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """Send the robot to its safe position; the cell stays IDLE (maintenance role)."""
    command(ctx, json_flag, lambda c: c.home())


def purge(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """Purge the glue line at the purge position; the cell stays IDLE (maintenance role)."""
    command(ctx, json_flag, lambda c: c.purge())


def jog(
    ctx: typer.Context,
    axis: Annotated[str, typer.Argument(help="x, y or z (robot base frame).")],
    distance_mm: Annotated[
        float, typer.Argument(help="The step in mm; a negative one after --: jog x -- -5.")
    ],
    json_flag: JsonFlag = False,
) -> None:
    """Move the robot one bounded step, in IDLE (maintenance role)."""
    command(ctx, json_flag, lambda c: c.jog(axis, distance_mm))


def history(
    ctx: typer.Context,
    limit: Annotated[
        int, typer.Option("--limit", min=1, max=10_000, help="How many transitions.")
    ] = 20,
    json_flag: JsonFlag = False,
) -> None:
    """The latest state transitions, newest first."""
    options = options_for(ctx, json_flag)
    show(options, call(options, lambda c: c.history(limit)), history_table)


def allowed(
    ctx: typer.Context,
    command: Annotated[str, typer.Argument(help="A command name, e.g. start or calibrate-robot.")],
    json_flag: JsonFlag = False,
) -> None:
    """Would COMMAND be accepted now? Exit 0 if yes, 3 if not; the reason either way."""
    options = options_for(ctx, json_flag)
    answer = call(options, lambda c: c.allowed(command))
    if options.json:
        print_json(answer)
    else:
        typer.echo(answer.get("reason", ""))
    if not answer.get("allowed"):
        raise typer.Exit(EXIT_REFUSED)


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
    options = options_for(ctx, json_flag)
    try:
        wanted = normalize_state(state)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="STATE") from None
    fail_on = ("ERROR",) if fail_on_error else ()
    reached = call(
        options,
        lambda c: c.wait_for_state(wanted, timeout, poll_interval=interval, fail_on=fail_on),
    )
    if options.json:
        print_json(reached)
    else:
        typer.echo(reached["state"])
