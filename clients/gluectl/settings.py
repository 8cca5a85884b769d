"""gluectl's `settings` group: `get` shows the table of settings with where each value
comes from; `set` turns NAME=VALUE words into a PATCH /settings body.
"""

from __future__ import annotations

import json
from typing import Annotated, Any

import typer
from rich.table import Table
from rich.text import Text

from clients.gluectl.calls import call, options_for, print_json, show
from clients.gluectl.format import value as _value
from clients.gluectl.options import JsonFlag

META_KEYS = ("sources", "runtime_settings")


def settings_rows(data: dict[str, Any], names: list[str] | None = None) -> list[dict[str, Any]]:
    """One row per setting of GET /settings (or only `names`): name, value, source, and
    whether a change applies at once (`runtime`) or needs a restart.

    Raises KeyError naming a setting in `names` the server does not have."""
    sources = data.get("sources") or {}
    runtime = set(data.get("runtime_settings") or ())
    wanted = names or [key for key in data if key not in META_KEYS]
    rows = []
    for name in wanted:
        if name not in data or name in META_KEYS:
            raise KeyError(name)
        rows.append(
            {
                "name": name,
                "value": data[name],
                "source": sources.get(name, "unknown"),
                "changes": "at once" if name in runtime else "at a restart",
            }
        )
    return rows


def settings_table(rows: list[dict[str, Any]]) -> Table:
    table = Table(title="settings", title_justify="left")
    for column in ("setting", "value", "from", "a change applies"):
        table.add_column(column, overflow="fold")
    for row in rows:
        value = json.dumps(row["value"], ensure_ascii=False)
        table.add_row(*(Text(v) for v in (row["name"], value, row["source"], row["changes"])))
    return table


def parse_assignments(words: list[str]) -> dict[str, Any]:
    """`NAME=VALUE` words as a body: each value read as JSON (10, true, 2.5), else as text
    (INFO). ValueError for a word without `=` or with an empty name."""
    body: dict[str, Any] = {}
    for word in words:
        name, equals, text = word.partition("=")
        if not equals or not name.strip():
            raise ValueError(f"{word!r}: expected NAME=VALUE, e.g. shift_hours=10")
        try:
            body[name.strip()] = json.loads(text)
        except ValueError:
            body[name.strip()] = text
    return body


settings_app = typer.Typer(help="The settings in force, and the runtime ones changed (admin).")


@settings_app.command("get")
def settings_get(
    ctx: typer.Context,
    names: Annotated[
        list[str] | None, typer.Argument(help="Settings to show (all if none).")
    ] = None,
    json_flag: JsonFlag = False,
) -> None:
    """Each setting's value, where it comes from, and whether a change applies at once."""
    options = options_for(ctx, json_flag)
    data = call(options, lambda c: c.settings())
    try:
        rows = settings_rows(data, names or None)
    except KeyError as missing:
        raise typer.BadParameter(
            f"{missing.args[0]} names no setting", param_hint="NAMES"
        ) from None
    show(options, rows, settings_table)


@settings_app.command("set")
def settings_set(
    ctx: typer.Context,
    assignments: Annotated[list[str], typer.Argument(help="NAME=VALUE, e.g. shift_hours=10.")],
    json_flag: JsonFlag = False,
) -> None:
    """Change runtime settings at once; they are saved and stay over a restart."""
    options = options_for(ctx, json_flag)
    try:
        body = parse_assignments(assignments)
    except ValueError as error:
        raise typer.BadParameter(str(error), param_hint="NAME=VALUE") from None
    answer = call(options, lambda c: c.change_settings(**body))
    if options.json:
        print_json(answer)
        return
    changed = answer.get("changed") or {}
    for name, change in changed.items():
        typer.echo(f"{name}: {_value(change['old'])} -> {_value(change['new'])} (saved)")
    if not changed:
        typer.echo("nothing changed: each value was in force already")
