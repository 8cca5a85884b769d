"""Run every benchmark: `python -m bench` (or `make bench`).

Each prints a table and a JSON line, and writes bench/results/<name>.json.
"""

from __future__ import annotations

from bench import device_latency, engine_throughput, journal, vision


def main() -> None:
    engine_throughput.main([])
    device_latency.main([])
    vision.main([])
    journal.main([])


if __name__ == "__main__":
    main()
