"""Run every benchmark: `python -m bench` (or `make bench`).

Each runs as `python -m bench.<name>` in a process of its own, so no benchmark
inherits another's memory, threads or collector state; each prints a table
and a JSON line and writes bench/results/<name>.json (the scaling sweep also
bench/results/scaling.png). With the default counts the whole run takes about
25 minutes on two cores; `python -m bench.<name> --help` for smaller runs, and
`python -m bench.markdown` prints the results as Markdown tables.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = (
    ("engine_throughput", ["--profile"]),
    ("device_latency", []),
    ("device_feed", []),
    ("estop_latency", []),
    ("estop_under_attack", []),
    ("estop_doors", []),
    ("reset_probe", []),
    ("pause_latency", []),
    ("ws_fanout", []),
    ("rest_throughput", []),
    ("memory", []),
    ("self_watch", []),
    ("memory", ["--cell"]),
    ("scaling", []),
    ("vision", []),
    ("vision_accuracy", []),
    ("bead_inspection", []),
    ("journal", []),
    ("journal_verify", []),
    ("startup", []),
    ("planning", []),
    ("plant_latency", []),
    ("line_scale", []),
    ("cycle_time", []),
    ("recording_cost", []),
)


def main() -> int:
    failed = []
    for name, args in BENCHMARKS:
        print(f"\n=== bench.{name} {' '.join(args)}", flush=True)
        result = subprocess.run([sys.executable, "-m", f"bench.{name}", *args], cwd=ROOT)
        if result.returncode != 0:
            failed.append(name)
    if failed:
        print(f"\nfailed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
