"""Run every benchmark: `python -m bench` (or `make bench`).

Each prints a table and a JSON line, and writes bench/results/<name>.json (the
scaling sweep also bench/results/scaling.png). With the default counts the
whole run takes about 25 minutes on two cores; every module also runs alone
with smaller counts (`python -m bench.<name> --help`).
"""

from __future__ import annotations

from bench import (
    device_latency,
    engine_throughput,
    estop_latency,
    journal,
    memory,
    rest_throughput,
    scaling,
    vision,
    ws_fanout,
)


def main() -> None:
    engine_throughput.main(["--profile"])
    device_latency.main([])
    estop_latency.main([])
    ws_fanout.main([])
    rest_throughput.main([])
    memory.main([])
    scaling.main([])
    vision.main([])
    journal.main([])


if __name__ == "__main__":
    main()
