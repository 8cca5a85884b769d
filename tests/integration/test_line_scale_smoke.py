"""The line benchmark (bench/line_scale.py) runs end to end on a line of two cells.

Debian's mosquitto, two `python -m server` cells, the line view in Debian's Chromium
and a stop witness, all real processes on loopback, as in tests/integration/
test_bench_smoke.py: no timing is asserted, only that every figure was measured and
is coherent (each transition seen by the subscriber, the screen showing them, each
stop timed, traffic and memory counted per cell). Results go to tmp_path. The
temporary directory stays the machine's: Chromium's socket path under a test's
own would be too long for it.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench import line_scale
from bench.report import RESULTS_ENV


@pytest.fixture
def results_in_tmp(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv(RESULTS_ENV, str(tmp_path))
    return tmp_path


def test_line_scale_measures_every_figure_on_two_cells(results_in_tmp: Path) -> None:
    """One cell runs an order, the other is stopped and reset through its witness:
    transitions reach the subscriber and the line view's screen, every stop is timed,
    both cells' traffic, memory and CPU are counted."""
    rows = line_scale.main(
        ["--cells", "2", "--busy", "1", "--witnessed", "1", "--seconds", "8", "--stop-every", "1"]
    )
    figures = {row["figure"]: row for row in rows}
    latency = [row for name, row in figures.items() if name.startswith(("transition", "device"))]
    assert len(latency) == 3, list(figures)
    for row in latency:
        assert row["n"] > 0, row
        assert 0 < row["p50_ms"] <= row["p99_ms"] <= row["max_ms"]
    traffic = [row for name, row in figures.items() if name.startswith("traffic")]
    assert len(traffic) == 2 and all(row["messages_per_s"] > 0 for row in traffic), traffic
    cells = [row for name, row in figures.items() if name.startswith("per cell")]
    assert len(cells) == 2 and all(row["unique_mb"] > 0 for row in cells), cells
    written = json.loads((results_in_tmp / "line_scale.json").read_text(encoding="utf-8"))
    assert written["rows"] == rows
    assert written["transitions"] >= written["transitions_not_seen_on_screen"]
