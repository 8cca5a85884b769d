"""A report as one printable HTML page, its charts inline SVG (GET /reports/{id}?format=html).

Pure: the report's JSON in, a whole page out, nothing fetched, so it prints, mails and
archives as it is. Every text from the journal (fault messages, codes) is escaped.
A4 portrait at print: the figures, then OEE's factors, parts hour by hour, time in
each state, the stop reasons and the alerts.
"""

from __future__ import annotations

import html
import time
from collections.abc import Sequence
from typing import Any

GOOD, BAD, NEUTRAL = "#2e7d32", "#c62828", "#546e7a"
STATE_COLOURS = {
    "EXECUTING_TRAJECTORY": "#2e7d32",
    "IDLE": "#90a4ae",
    "PAUSED": "#f9a825",
    "ERROR": "#c62828",
    "INITIALIZING": "#6d4c41",
}
OTHER_STATE = "#1565c0"

STYLE = """
body { font: 13px/1.4 system-ui, sans-serif; color: #111; margin: 24px; max-width: 760px; }
h1 { font-size: 20px; margin: 0 0 4px; } h2 { font-size: 15px; margin: 18px 0 6px; }
.muted { color: #555; } table { border-collapse: collapse; width: 100%; }
td, th { border-bottom: 1px solid #ddd; padding: 3px 6px; text-align: left; }
th { font-weight: 600; } td.n { text-align: right; font-variant-numeric: tabular-nums; }
.figures { display: flex; gap: 18px; flex-wrap: wrap; }
.figure b { display: block; font-size: 22px; } svg { display: block; }
@media print { body { margin: 10mm; } @page { size: A4 portrait; margin: 10mm; } }
"""


def _e(value: Any) -> str:
    return html.escape(str(value), quote=True)


def _pct(value: Any) -> str:
    return "—" if not isinstance(value, int | float) else f"{100 * value:.1f} %"


def _clock(t: float) -> str:
    return time.strftime("%Y-%m-%d %H:%M", time.localtime(t))


def _span(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def factor_bars(oee: dict[str, Any] | None) -> str:
    """OEE and its factors as horizontal bars out of 100 %."""
    rows = [("availability", "availability"), ("performance", "performance")]
    rows += [("quality", "quality"), ("OEE", "oee")]
    width, bar_h, label_w = 520, 20, 110
    parts = [
        f'<svg width="{width}" height="{len(rows) * (bar_h + 6)}" role="img" aria-label="OEE">'
    ]
    for k, (label, key) in enumerate(rows):
        value = (oee or {}).get(key)
        y = k * (bar_h + 6)
        length = 0 if not isinstance(value, int | float) else max(0.0, min(1.0, value)) * 330
        colour = GOOD if key == "oee" else NEUTRAL
        parts.append(f'<text x="0" y="{y + 15}" font-size="12">{label}</text>')
        parts.append(f'<rect x="{label_w}" y="{y}" width="330" height="{bar_h}" fill="#eee"/>')
        parts.append(
            f'<rect x="{label_w}" y="{y}" width="{length:.1f}" height="{bar_h}" fill="{colour}"/>'
        )
        parts.append(f'<text x="{label_w + 340}" y="{y + 15}" font-size="12">{_pct(value)}</text>')
    parts.append("</svg>")
    return "".join(parts)


def hourly_bars(hours: Sequence[dict[str, Any]]) -> str:
    """Parts good (green) and defective (red) per hour, stacked."""
    width, height, base = 700, 150, 130
    top = max([h["good"] + h["defective"] for h in hours] + [1])
    step = width / max(1, len(hours))
    parts = [f'<svg width="{width}" height="{height}" role="img" aria-label="parts per hour">']
    for k, hour in enumerate(hours):
        x = k * step + 2
        good_h = hour["good"] / top * (base - 10)
        bad_h = hour["defective"] / top * (base - 10)
        w = max(1.0, step - 4)
        parts.append(
            f'<rect x="{x:.1f}" y="{base - good_h:.1f}" width="{w:.1f}" height="{good_h:.1f}" '
            f'fill="{GOOD}"><title>{hour["good"]} good</title></rect>'
        )
        parts.append(
            f'<rect x="{x:.1f}" y="{base - good_h - bad_h:.1f}" width="{w:.1f}" '
            f'height="{bad_h:.1f}" fill="{BAD}"><title>{hour["defective"]} defective</title></rect>'
        )
        parts.append(
            f'<text x="{x:.1f}" y="{height - 4}" font-size="10">'
            f"{time.strftime('%H:%M', time.localtime(hour['start']))}</text>"
        )
    parts.append(f'<text x="{width - 4}" y="10" font-size="10" text-anchor="end">max {top}</text>')
    parts.append("</svg>")
    return "".join(parts)


def state_strip(seconds: dict[str, float] | None) -> str:
    """The window's time in each state as one stacked bar, with a legend."""
    seconds = {k: v for k, v in (seconds or {}).items() if v > 0}
    total = sum(seconds.values())
    width = 700
    parts = [f'<svg width="{width}" height="46" role="img" aria-label="time in each state">']
    x = 0.0
    legend_x = 0
    for state, value in sorted(seconds.items(), key=lambda kv: -kv[1]):
        w = value / total * width if total else 0
        colour = STATE_COLOURS.get(state, OTHER_STATE)
        parts.append(
            f'<rect x="{x:.1f}" y="0" width="{w:.1f}" height="20" fill="{colour}">'
            f"<title>{_e(state)} {_span(value)}</title></rect>"
        )
        parts.append(f'<rect x="{legend_x}" y="28" width="10" height="10" fill="{colour}"/>')
        label = f"{state.lower().replace('_', ' ')} {_span(value)}"
        parts.append(f'<text x="{legend_x + 14}" y="37" font-size="11">{_e(label)}</text>')
        legend_x += 14 + 7 * len(label) + 12
        x += w
    parts.append("</svg>")
    return "".join(parts)


def _stop_rows(stops: Sequence[dict[str, Any]]) -> str:
    if not stops:
        return '<p class="muted">No fault stopped the cell.</p>'
    longest = max(s["seconds"] for s in stops) or 1
    rows = "".join(
        f"<tr><td>{_e(s['code'])}</td><td>{_e(s['component'])}</td><td class=n>{s['count']}</td>"
        f'<td class=n>{_span(s["seconds"])}</td><td><svg width="140" height="10">'
        f'<rect width="{140 * s["seconds"] / longest:.1f}" height="10" fill="{BAD}"/></svg></td>'
        f"<td>{_e(s['message'])}</td></tr>"
        for s in stops
    )
    head = "<tr><th>fault</th><th>device</th><th>times</th><th>in ERROR</th><th></th>"
    return f"<table>{head}<th>first message</th></tr>{rows}</table>"


def _alert_rows(alerts: dict[str, Any]) -> str:
    listed = alerts.get("by_code") or []
    if not listed:
        return '<p class="muted">No alert was raised.</p>'
    rows = "".join(
        f"<tr><td>{_e(a['code'])}</td><td>{_e(a['component'])}</td><td class=n>{a['count']}</td>"
        f"<td>{_e(a.get('last_message', ''))}</td></tr>"
        for a in listed
    )
    head = "<tr><th>alert</th><th>from</th><th>times</th><th>last message</th></tr>"
    return f"<table>{head}{rows}</table>"


def _maintenance(care: dict[str, Any]) -> str:
    """The maintenance due when the report was made, in words."""
    due = [
        f"{_e(i['name'])}: {_e(i['status'])} ({_e(i['reason'])})" for i in care.get("items_due", [])
    ]
    for what in ("pot_life", "glue_level"):
        status = care.get(what, "off")
        if status not in ("off", "ok"):
            due.append(f"{what.replace('_', ' ')}: {_e(status)}")
    return "; ".join(due) if due else '<span class="muted">nothing due</span>'


def report_page(report: dict[str, Any]) -> str:
    """The whole printable page of `report` (GET /reports/{id}'s JSON)."""
    window = report["window"]
    parts = report["parts"]
    oee = report.get("oee") or {}
    title = f"{report['period'].capitalize()} report · {report['cell_id']}"
    maintenance = _maintenance(report.get("maintenance") or {})
    figures = "".join(
        f'<div class="figure"><b>{value}</b>{_e(label)}</div>'
        for label, value in (
            ("good parts", parts["good"]),
            ("defective parts", parts["defective"]),
            ("OEE", _pct(oee.get("oee"))),
            ("stops", sum(s["count"] for s in report["stop_reasons"])),
            ("alerts", report["alerts"]["count"]),
        )
    )
    return (
        "<!doctype html><html lang=en><head><meta charset=utf-8>"
        f"<title>{_e(title)}</title><style>{STYLE}</style></head><body>"
        f"<h1>{_e(title)}</h1>"
        f'<p class="muted">{_clock(window["start"])} to {_clock(window["end"])} · report '
        f"{_e(report.get('id', ''))} made {_clock(report['generated_at'])}</p>"
        f'<div class="figures">{figures}</div>'
        f"<h2>OEE and its factors</h2>{factor_bars(report.get('oee'))}"
        f"<h2>Parts per hour</h2>{hourly_bars(parts['by_hour'])}"
        f"<h2>Time in each state</h2>{state_strip(report.get('time_in_state_s'))}"
        f"<h2>Stop reasons (most time first)</h2>{_stop_rows(report['stop_reasons'])}"
        f"<h2>Alerts raised</h2>{_alert_rows(report['alerts'])}"
        f"<h2>Maintenance due</h2><p>{maintenance}</p>"
        "</body></html>"
    )
