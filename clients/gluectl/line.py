"""`gluectl line`: every cell of a line, read from its MQTT broker (clients/line_watch.py),
shown once or followed live.
"""

from __future__ import annotations

import sys
import threading
from typing import Annotated

import typer
from rich.console import Console
from rich.live import Live

from clients.client import Unreachable
from clients.gluectl.calls import fail, options_for, print_json, stdout
from clients.gluectl.exit_codes import EXIT_OK
from clients.gluectl.options import JsonFlag, Options
from clients.line_model import DEFAULT_PREFIX, LineModel
from clients.line_table import line_table
from clients.line_watch import Broker, LineUnreachable, LineWatcher


def _line_show(options: Options, console: Console, model: LineModel, broker: Broker) -> None:
    if options.json:
        print_json(model.as_json())
    else:
        console.print(line_table(model, str(broker)))
    sys.stdout.flush()


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
    options = options_for(ctx, json_flag)
    try:
        broker = Broker.parse(broker_url)
    except ValueError as error:
        raise typer.BadParameter(str(error), param_hint="--broker") from None
    console = stdout()
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
        fail(options, Unreachable(str(error)))
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
