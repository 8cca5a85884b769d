"""gluectl's tables of the shift and daily reports (GET /reports, GET /reports/{id})."""

from __future__ import annotations

from typing import Any

from rich.table import Table
from rich.text import Text

from clients.gluectl_format import key_values as _key_values
from clients.gluectl_format import value as _value
from clients.gluectl_format import when as _when


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
