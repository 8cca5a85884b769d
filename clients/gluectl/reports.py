"""gluectl's reading commands of production and upkeep: `kpis`, the `report` group (shift
and daily reports, GET /reports), `maintenance` (wear counters and schedule) and
`health` (each device's link), with their tables.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.table import Table
from rich.text import Text

from clients.gluectl.calls import call, options_for, show, stdout
from clients.gluectl.exit_codes import EXIT_REFUSED
from clients.gluectl.format import key_values as _key_values
from clients.gluectl.format import value as _value
from clients.gluectl.format import when as _when
from clients.gluectl.options import JsonFlag, Options


def report_table(report: dict[str, Any]) -> Table:
    window = report.get("window") or {}
    title = (
        f"{report.get('period')} report {report.get('id')}: "
        f"{_when(window.get('start'))} → {_when(window.get('end'))}"
    )
    parts = report.get("parts") or {}
    oee = report.get("oee") or {}
    rows = [
        ("parts good", _value(parts.get("good"))),
        ("parts defective", _value(parts.get("defective"))),
        *((f"oee.{k}", _value(v)) for k, v in oee.items()),
        *(
            (f"stop {s['code']}", f"{s['count']}×, {_value(s['seconds'])} s in ERROR")
            for s in report.get("stop_reasons") or []
        ),
        ("alerts", _value((report.get("alerts") or {}).get("count"))),
        ("maintenance due", _maintenance(report.get("maintenance") or {})),
    ]
    return _key_values(title, rows)


def _maintenance(care: dict[str, Any]) -> str:
    due = [f"{i['name']} {i['status']}" for i in care.get("items_due", [])]
    due += [
        f"{what.replace('_', ' ')} {care[what]}"
        for what in ("pot_life", "glue_level")
        if care.get(what, "off") not in ("off", "ok")
    ]
    return ", ".join(due) or "nothing"


def reports_table(reports: list[dict[str, Any]]) -> Table:
    table = Table(title="reports, newest first", title_justify="left")
    for column in ("id", "period", "from", "to", "good", "defective", "oee"):
        table.add_column(column)
    for row in reports:
        window = row.get("window") or {}
        table.add_row(
            *(
                Text(v)
                for v in (
                    _value(row.get("id")),
                    _value(row.get("period")),
                    _when(window.get("start"), short=True),
                    _when(window.get("end"), short=True),
                    _value(row.get("parts_good")),
                    _value(row.get("parts_defective")),
                    _value(row.get("oee")),
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
    options = options_for(ctx, json_flag)
    if done is not None:
        call(options, lambda c: c.maintenance_done(done))
    if refill:
        call(options, lambda c: c.glue_refill())
    show(options, call(options, lambda c: c.maintenance()), maintenance_table)


def kpis(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """The current shift's KPIs and OEE."""
    options = options_for(ctx, json_flag)
    show(options, call(options, lambda c: c.kpis()), kpis_table)


report_app = typer.Typer(help="Shift and daily reports: parts, OEE, stop reasons, alerts.")


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
        latest = call(options, lambda c: c.reports(period, 1))
        if not latest:
            typer.echo(
                f"gluectl: no {period} report yet: one is made at each {period}'s end", err=True
            )
            raise typer.Exit(EXIT_REFUSED)
        report_id = int(latest[0]["id"])
    chosen = report_id
    if html is not None:
        html.write_text(call(options, lambda c: c.report_html(chosen)), encoding="utf-8")
        stdout().print(f"wrote {html}")
        return
    show(options, call(options, lambda c: c.report(chosen)), report_table)


@report_app.command("shift")
def report_shift(
    ctx: typer.Context, id_: IdOption = None, html: HtmlOption = None, json_flag: JsonFlag = False
) -> None:
    """The latest shift's report (or --id's): parts, OEE, stop reasons, alerts."""
    _report(options_for(ctx, json_flag), "shift", id_, html)


@report_app.command("day")
def report_day(
    ctx: typer.Context, id_: IdOption = None, html: HtmlOption = None, json_flag: JsonFlag = False
) -> None:
    """The latest production day's report (or --id's)."""
    _report(options_for(ctx, json_flag), "day", id_, html)


@report_app.command("list")
def report_list(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """The reports kept, newest first."""
    options = options_for(ctx, json_flag)
    show(options, call(options, lambda c: c.reports()), reports_table)


def health(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """Each device's link, last round trip and last error (needs no token)."""
    options = options_for(ctx, json_flag)
    show(options, call(options, lambda c: c.health()), health_table)
