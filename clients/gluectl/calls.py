"""How a gluectl command reaches the cell and what it prints: a query over HTTP, a
command over HTTP (or signed over MQTT with --mqtt), the answer as a table or as JSON,
and each client error as its reason on stderr and its exit code.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import replace
from typing import Any, NoReturn, TypeVar

import typer
from rich.console import Console, RenderableType

from clients.client import Busy, CellClient, CellError, CommandResult, Unauthorized
from clients.gluectl.exit_codes import (
    EXIT_AUTH,
    EXIT_BUSY,
    EXIT_FAULTED,
    EXIT_INVALID,
    EXIT_REFUSED,
    EXIT_TIMEOUT,
    EXIT_UNREACHABLE,
    exit_code,
)
from clients.gluectl.options import Options

T = TypeVar("T")

PIPED_WIDTH = 160  # columns of a table when stdout is not a terminal


def options_for(ctx: typer.Context, json_flag: bool) -> Options:
    """The global options, with the command's own --json (after the command) applied."""
    options: Options = ctx.obj
    return replace(options, json=True) if json_flag else options


def stdout() -> Console:
    """Rich output; piped (a file, grep, less) tables take their natural width, not 80."""
    console = Console(highlight=False, soft_wrap=False)
    if not console.is_terminal and "COLUMNS" not in os.environ:
        console = Console(highlight=False, soft_wrap=False, width=PIPED_WIDTH)
    return console


def print_json(data: Any) -> None:
    """One JSON document on stdout."""
    typer.echo(json.dumps(data, ensure_ascii=False, default=str))


def fail(options: Options, error: CellError) -> NoReturn:
    """Report `error` (reason on stderr, JSON on stdout with --json) and exit with its code."""
    code = exit_code(error)
    if options.json:
        print_json(error.as_dict())
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


def call(options: Options, action: Callable[[CellClient], T]) -> T:
    """Ask the HTTP API (queries never go over MQTT); an error exits through `fail`."""
    if options.mqtt is not None:
        raise typer.BadParameter(
            "only commands go over MQTT; ask the cell's HTTP API (--url) for the rest",
            param_hint="--mqtt",
        )
    try:
        with options.client() as client:
            return action(client)
    except CellError as error:
        fail(options, error)


def command(ctx: typer.Context, json_flag: bool, action: Callable[[Any], CommandResult]) -> None:
    """Run a command (over HTTP, or signed over MQTT with --mqtt); print the decision.
    Refusals and errors exit through `fail`."""
    options = options_for(ctx, json_flag)
    try:
        with options.command_client() as client:
            result = action(client)
    except CellError as error:
        fail(options, error)
    except ValueError as error:  # e.g. no token to sign with, or not an API token
        raise typer.BadParameter(str(error), param_hint="--token") from None
    if options.json:
        print_json(result.as_dict())
    else:
        event = f"  (event {result.event_id})" if result.event_id else ""
        typer.echo(f"{result.message}{event}")


def show(options: Options, data: Any, render: Callable[[Any], RenderableType]) -> None:
    """An answer as JSON with --json, else as `render` draws it."""
    if options.json:
        print_json(data)
    else:
        stdout().print(render(data))
