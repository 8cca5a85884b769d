"""Print the latest results (bench/results/*.json) as Markdown tables.

`python -m bench.markdown [name ...]`: for pasting into docs/benchmarks.md and
the README after a run, so the published figures are copied, not retyped.
"""

from __future__ import annotations

import json
import sys
from typing import Any

from bench.report import results_path


def table(rows: list[dict[str, Any]]) -> str:
    columns = list(dict.fromkeys(key for row in rows for key in row))
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for row in rows:
        lines.append("| " + " | ".join(_cell(row.get(column)) for column in columns) + " |")
    return "\n".join(lines)


def _cell(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:,.3f}".rstrip("0").rstrip(".") if value < 1000 else f"{value:,.0f}"
    if isinstance(value, int):
        return f"{value:,}"
    return "" if value is None else str(value)


def main(names: list[str]) -> None:
    if names:
        paths = [results_path(f"{name}.json") for name in names]
    else:
        paths = sorted(results_path("any.json").parent.glob("*.json"))
    for path in paths:
        document = json.loads(path.read_text(encoding="utf-8"))
        machine = document.get("machine", {})
        print(f"### {document['benchmark']} ({document.get('time', '')})\n")
        print(
            f"{machine.get('cpu_count')} cores, {machine.get('processor')}, "
            f"Python {machine.get('python')}, {machine.get('platform')}\n"
        )
        print(table(document["rows"]))
        print()


if __name__ == "__main__":
    main(sys.argv[1:])
