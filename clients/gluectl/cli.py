"""gluectl's command line put together: the typer app, its global options, every command
and group in the order `gluectl --help` lists them, and the console entry point.

The commands live by concern in the sibling modules (`cell`, `workpieces`, `orders`,
`reports`, `settings`, `watch`, `line`); registering them here, in one list, keeps the
help's order in one place.
"""

from __future__ import annotations

import sys

import typer

from clients.gluectl import cell, line, orders, reports, settings, watch, workpieces
from clients.gluectl.calls import print_json
from clients.gluectl.exit_codes import EXIT_CODES_HELP, EXIT_ERROR, EXIT_OK, EXIT_USAGE
from clients.gluectl.options import main_options

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
app.callback()(main_options)

# Top-level commands first, then the groups, each in the order the help lists them.
app.command()(cell.state)
app.command()(cell.start)
app.command()(cell.pause)
app.command()(cell.resume)
app.command()(cell.cancel)
app.command()(cell.estop)
app.command()(cell.reset)
app.command()(cell.home)
app.command()(cell.purge)
app.command()(reports.maintenance)
app.command()(cell.jog)
app.command("calibrate-robot")(workpieces.calibrate_robot)
app.command("calibrate-camera")(workpieces.calibrate_camera)
app.command("create-workpiece")(workpieces.create_workpiece)
app.command()(workpieces.workpieces)
app.command()(cell.history)
app.command()(reports.kpis)
app.command()(reports.health)
app.command()(cell.allowed)
app.command()(cell.wait)
app.command()(watch.watch)
app.command()(line.line)
app.add_typer(workpieces.marker_app, name="marker")
app.add_typer(orders.order_app, name="order")
app.add_typer(reports.report_app, name="report")
app.add_typer(settings.settings_app, name="settings")


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
        print_json({"error": "UsageError", "status_code": None, "message": message})
        typer.echo(f"gluectl: usage error: {message}", err=True)
        sys.exit(EXIT_USAGE if error.exit_code == EXIT_USAGE else EXIT_ERROR)
    except typer.Abort:
        sys.exit(EXIT_ERROR)
    sys.exit(code if isinstance(code, int) else EXIT_OK)
