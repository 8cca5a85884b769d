"""`gluectl watch`: the live view over /ws. On a terminal a panel redrawn in place (state,
progress bar, timeline); piped, one line (or one JSON message) per message.
"""

from __future__ import annotations

import asyncio
import json
import sys
import time
from collections import deque
from typing import Annotated, Any

import typer
from rich.console import Group, RenderableType
from rich.live import Live
from rich.panel import Panel
from rich.progress_bar import ProgressBar
from rich.table import Table
from rich.text import Text

from clients.client import CellError
from clients.gluectl.calls import fail, options_for, print_json, stdout
from clients.gluectl.exit_codes import EXIT_OK
from clients.gluectl.format import fault_line, progress_line
from clients.gluectl.format import value as _value
from clients.gluectl.format import when as _when
from clients.gluectl.options import JsonFlag, Options


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
                Text(progress_line(progress) or "starting"),
            )
            parts.append(bar)
        if self.fault and self.state == "ERROR":
            parts.append(Text(f"fault {fault_line(self.fault)}", style="red"))
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
        return f"{prefix}  {message.get('operation')}  {progress_line(message)}".rstrip()
    if kind == "error":
        return f"{prefix}  {message.get('code')}: {message.get('message')}"
    return f"{prefix}  {json.dumps(message, ensure_ascii=False)}"


async def _watch(options: Options, count: int | None, types: list[str] | None) -> None:
    console = stdout()
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
                        print_json(message)
                    else:
                        typer.echo(message_line(message))
                    sys.stdout.flush()
                    if count is not None and received >= count:
                        break
            finally:
                if live:
                    live.stop()


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
    options = options_for(ctx, json_flag)
    try:
        asyncio.run(_watch(options, count, types))
    except CellError as error:
        fail(options, error)
    except KeyboardInterrupt:
        raise typer.Exit(EXIT_OK) from None
