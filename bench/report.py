"""Shared output for benchmarks: a table on stdout and a JSON file under bench/results/.

The JSON goes elsewhere when `emit` is given `results_dir`, or when the
environment sets BENCH_RESULTS_DIR: smoke tests run the benchmarks with tiny
counts and must not overwrite the published figures.
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import time
from pathlib import Path
from typing import Any

RESULTS = Path(__file__).resolve().parent / "results"
RESULTS_ENV = "BENCH_RESULTS_DIR"


def machine() -> dict[str, Any]:
    return {
        "python": platform.python_version(),
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(terse=True),
        "processor": platform.processor() or platform.machine(),
    }


def percentiles_ms(samples_s: list[float]) -> dict[str, float]:
    """p50, p99 and max of durations given in seconds, in milliseconds."""
    ordered = sorted(samples_s)
    if not ordered:
        return {"p50_ms": float("nan"), "p99_ms": float("nan"), "max_ms": float("nan"), "n": 0}
    p99 = ordered[min(len(ordered) - 1, int(0.99 * len(ordered)))]
    return {
        "p50_ms": round(statistics.median(ordered) * 1000, 3),
        "p99_ms": round(p99 * 1000, 3),
        "max_ms": round(ordered[-1] * 1000, 3),
        "n": len(ordered),
    }


def results_path(filename: str, results_dir: Path | None = None) -> Path:
    """Where a result file goes: `results_dir`, else $BENCH_RESULTS_DIR, else bench/results."""
    directory = results_dir or Path(os.environ.get(RESULTS_ENV) or RESULTS)
    directory.mkdir(parents=True, exist_ok=True)
    return directory / filename


def emit(
    name: str,
    rows: list[dict[str, Any]],
    extra: dict[str, Any] | None = None,
    results_dir: Path | None = None,
) -> Path:
    """Print `rows` as a table and write them, with the machine, to <results>/<name>.json.

    <results> is `results_dir`, else $BENCH_RESULTS_DIR, else bench/results.
    """
    columns = list(dict.fromkeys(key for row in rows for key in row))
    widths = {c: max(len(c), *(len(_fmt(row.get(c))) for row in rows)) for c in columns}
    print(f"\n{name}")
    print("  ".join(c.ljust(widths[c]) for c in columns))
    print("  ".join("-" * widths[c] for c in columns))
    for row in rows:
        print("  ".join(_fmt(row.get(c)).ljust(widths[c]) for c in columns))
    path = results_path(f"{name}.json", results_dir)
    document = {
        "benchmark": name,
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "machine": machine(),
        "rows": rows,
        **(extra or {}),
    }
    path.write_text(json.dumps(document, indent=2), encoding="utf-8")
    print(json.dumps(document))
    return path


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:,.3f}" if value < 1000 else f"{value:,.0f}"
    return "" if value is None else str(value)
