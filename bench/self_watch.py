"""The self-watch's own cost: one look at the cell's processes and disk, and judging one
part on the quality charts, in the server's process.

The look's reads (`/proc`, the disk) run off the event loop every `watch_interval_s`;
the judging of what they found, and of each part as its run ends (the drift rule over
five charts of up to 200 parts), runs on it. Both are timed here with the server's
modules imported and the image process started, as in a running server.

    python -m bench.self_watch [--looks 200] [--parts 200]
"""

from __future__ import annotations

import argparse
import random
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.report import emit, percentiles_ms
from server.quality.trends import Point
from server.settings.watch import WatchSettings
from server.vision.process import IMAGE_PROCESS
from server.watch.watcher import CellWatch


def _quiet(code: str, message: str, component: str, **how: Any) -> None:
    """Warnings are not the figure here."""


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--looks", type=int, default=200)
    parser.add_argument("--parts", type=int, default=200)
    args = parser.parse_args(argv)
    IMAGE_PROCESS.warm_up()
    settings = WatchSettings()
    with tempfile.TemporaryDirectory() as data:
        watch = CellWatch(
            lambda: settings,
            Path(data),
            lambda: {"robot": {"last_rtt_ms": 1.0}, "glue": {"last_rtt_ms": 2.0}},
            _quiet,
        )
        for _ in range(20):  # the image process up, its pid known
            if IMAGE_PROCESS.pids():
                break
            time.sleep(0.25)
        reads, judges = [], []
        for _ in range(args.looks):
            started = time.perf_counter()
            figures = watch._read()
            read = time.perf_counter()
            watch._judge(*figures)
            judges.append(time.perf_counter() - read)
            reads.append(read - started)
        noise = random.Random(0)
        parts = []
        for index in range(args.parts):
            figures = {
                "bead_width_percent": 100 + noise.gauss(0, 2),
                "glue_volume_percent": 100 + noise.gauss(0, 1.5),
                "dispensing_cv_percent": 2 + noise.gauss(0, 0.2),
                "precision_p95_mm": 0.3 + noise.gauss(0, 0.02),
                "vision_residual_mm": 0.1 + noise.gauss(0, 0.01),
            }
            started = time.perf_counter()
            watch.add_part(Point(f"r{index}", float(index), True, figures))
            parts.append(time.perf_counter() - started)
        started = time.perf_counter()
        watch.trends()
        charts_s = time.perf_counter() - started
    IMAGE_PROCESS.close()
    rows = [
        {"step": "look: read /proc and the disk (off the loop)", **percentiles_ms(reads)},
        {"step": "look: judge (on the loop)", **percentiles_ms(judges)},
        {"step": "part: the drift rule on 5 charts (on the loop)", **percentiles_ms(parts)},
        {"step": "GET /quality/trends body (200 parts)", **percentiles_ms([charts_s])},
    ]
    emit("self_watch", rows, {"looks": args.looks, "parts": args.parts})
    return rows


if __name__ == "__main__":
    main()
