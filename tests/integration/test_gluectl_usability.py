"""gluectl for a person reading it: the live view after a reset, errors a script can
parse, help that reads right on an 80-column terminal.

Against a real server on loopback (the core on in-process fakes, as in
test_gluectl.py), gluectl as a subprocess where its output is what is tested.
"""

from __future__ import annotations

import json
import re
from typing import Any

import pytest
from rich.console import Console

from clients.gluectl.cli import app
from clients.gluectl.exit_codes import EXIT_REFUSED, EXIT_USAGE
from clients.gluectl.watch import WatchView

# `cli` is the fixture: a real server on loopback and gluectl pointed at it.
from tests.integration.test_gluectl import Cli, cli, gluectl_process  # noqa: F401


def _screen(view: WatchView) -> str:
    console = Console(record=True, width=120, force_terminal=False)
    console.print(view.render())
    return console.export_text()


async def test_watch_clears_the_fault_line_once_the_cell_is_reset(cli: Cli) -> None:  # noqa: F811
    """The live view, fed by the server's own /ws: fault, then reset, then no fault line."""
    view = WatchView(cli.url)
    async with cli.client.messages() as stream:
        messages = aiter(stream)

        async def until(done) -> None:  # type: ignore[no-untyped-def]
            while not done():
                view.update(await anext(messages))

        await until(lambda: view.state == "IDLE")
        await cli.client.estop("door open")
        await until(lambda: view.state == "ERROR" and view.fault is not None)
        assert "fault " in _screen(view)
        assert (await cli.client.reset()).accepted
        await until(lambda: view.state == "IDLE")
    shown = _screen(view)
    assert "state IDLE" in shown
    assert "fault " not in shown, shown


# --- --json: one document, whatever went wrong ---------------------------------------------


@pytest.mark.parametrize(
    "args",
    [
        ("--json", "--no-such-option"),
        ("--json", "wait"),  # missing argument
        ("wait", "NOWHERE", "--json"),  # bad argument, --json after the command
        ("--json", "history", "--limit", "0"),  # out of range
        ("--json", "start", "--contour-matching=x"),  # a flag given a value
    ],
)
async def test_usage_errors_with_json_are_one_json_document(args: tuple[str, ...]) -> None:
    ran = await gluectl_process(*args)
    assert ran.code == EXIT_USAGE, ran
    document = json.loads(ran.stdout)  # the whole of stdout, one document
    assert document["error"] == "UsageError" and document["message"], document
    assert "Usage:" not in ran.stdout + ran.stderr


async def test_a_server_error_with_json_is_one_json_document(cli: Cli) -> None:  # noqa: F811
    ran = await cli("--json", "resume")
    assert ran.code == EXIT_REFUSED
    assert json.loads(ran.stdout)["error"] == "Refused"


# --- help and version -------------------------------------------------------------------


def _commands() -> list[tuple[str, ...]]:
    """Every subcommand, those added later and those of groups (`marker list`) included."""
    import typer.main

    def walk(group: Any, path: tuple[str, ...]) -> list[tuple[str, ...]]:
        found = []
        for name, command in sorted(group.commands.items()):
            found.append((*path, name))
            if hasattr(command, "commands"):  # a group (typer's own, not click's class)
                found += walk(command, (*path, name))
        return found

    return walk(typer.main.get_command(app), ())


def _is_group(command: tuple[str, ...]) -> bool:
    import typer.main

    found: Any = typer.main.get_command(app)
    for name in command:
        found = found.commands[name]
    return hasattr(found, "commands")


@pytest.mark.parametrize("command", [(), *_commands()], ids=lambda c: " ".join(c) or "gluectl")
async def test_help_fits_80_columns_and_shows_booleans_as_flags(command: tuple[str, ...]) -> None:
    ran = await gluectl_process(*command, "--help", env={"COLUMNS": "80"})
    assert ran.code == 0, ran.stderr
    for line in ran.stdout.splitlines():
        assert len(line) <= 80, f"{len(line)} columns: {line!r}"
        assert "…" not in line, f"cut short: {line!r}"
    assert not re.search(r"<bool>|BOOLEAN|--json \S", ran.stdout), ran.stdout
    assert "--json" in ran.stdout or not command or _is_group(command)


async def test_version_comes_from_the_package_metadata() -> None:
    from importlib import metadata

    ran = await gluectl_process("--version")
    assert (ran.code, ran.stdout.strip()) == (0, f"gluectl {metadata.version('glue-cell-server')}")
