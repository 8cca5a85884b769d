"""Where the suite's time goes: the machine's CPU over the whole run, and per test.

At the end of every run the controller prints one line: the run's wall time and
how busy the machine's cores were meanwhile (from /proc/stat), so a reader can
tell a suite that waits from one that computes. On two cores, a run whose cores
were busy most of the time cannot get much shorter by running more tests at once:
only by doing less work.

With GLUE_TEST_CPU_REPORT set to a directory, each test process also writes one
JSON line per test there (its tier, wall time, and the CPU seconds of the test
process and of the child processes it waited for, set-up and teardown included);
`python -m tests.cpu_account DIR` sums them per tier.
"""

from __future__ import annotations

import json
import os
import resource
import sys
import time
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

REPORT_ENV = "GLUE_TEST_CPU_REPORT"


def machine_cpu() -> tuple[float, float] | None:
    """(busy, all) CPU seconds of every core since boot, or None off Linux."""
    try:
        fields = Path("/proc/stat").read_text().splitlines()[0].split()[1:]
    except OSError:
        return None
    ticks = [int(field) for field in fields[:8]]
    idle = ticks[3] + ticks[4]  # idle and iowait
    hertz = os.sysconf("SC_CLK_TCK")
    return (sum(ticks) - idle) / hertz, sum(ticks) / hertz


class CpuAccount:
    """The plugin: registered by tests/conftest.py."""

    def __init__(self, config: pytest.Config) -> None:
        self.controller = not hasattr(config, "workerinput")
        self.started = time.monotonic()
        self.cpu_at_start = machine_cpu()
        directory = os.environ.get(REPORT_ENV)
        self.rows = None
        if directory:
            Path(directory).mkdir(parents=True, exist_ok=True)
            name = getattr(config, "workerinput", {}).get("workerid", "main")
            self.rows = (Path(directory) / f"{name}-{os.getpid()}.jsonl").open("a")

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(self, item: pytest.Item) -> Iterator[None]:
        if self.rows is None:
            yield
            return
        wall, own, children = (
            time.monotonic(),
            _cpu(resource.RUSAGE_SELF),
            _cpu(resource.RUSAGE_CHILDREN),
        )
        yield
        row = {
            "test": item.nodeid,
            "tier": item.nodeid.split("/")[1] if item.nodeid.startswith("tests/") else "",
            "wall_s": round(time.monotonic() - wall, 3),
            "cpu_s": round(_cpu(resource.RUSAGE_SELF) - own, 3),
            "children_cpu_s": round(_cpu(resource.RUSAGE_CHILDREN) - children, 3),
        }
        self.rows.write(json.dumps(row) + "\n")
        self.rows.flush()

    def pytest_terminal_summary(self, terminalreporter: Any) -> None:
        end = machine_cpu()
        if not self.controller or self.cpu_at_start is None or end is None:
            return
        wall = time.monotonic() - self.started
        busy = end[0] - self.cpu_at_start[0]
        cores = os.cpu_count() or 1
        terminalreporter.write_line(
            f"machine CPU during this run: {busy:.0f} CPU-s busy in {wall:.0f} s wall on "
            f"{cores} cores ({busy / (wall * cores):.0%} of their time)"
        )


def _cpu(who: int) -> float:
    usage = resource.getrusage(who)
    return usage.ru_utime + usage.ru_stime


def summary(directory: Path) -> list[dict[str, Any]]:
    """Per tier: tests, wall seconds and CPU seconds summed over the tests."""
    tiers: dict[str, dict[str, float]] = defaultdict(lambda: defaultdict(float))
    for path in sorted(directory.glob("*.jsonl")):
        for line in path.read_text().splitlines():
            row = json.loads(line)
            tier = tiers[row["tier"]]
            tier["tests"] += 1
            tier["wall_s"] += row["wall_s"]
            tier["cpu_s"] += row["cpu_s"] + row["children_cpu_s"]
    return [
        {"tier": name, **{key: round(value, 1) for key, value in sums.items()}}
        for name, sums in sorted(tiers.items())
    ]


if __name__ == "__main__":
    rows = summary(Path(sys.argv[1]))
    print(f"{'tier':<12} {'tests':>6} {'wall_s':>9} {'cpu_s':>9}")
    for row in rows:
        print(f"{row['tier']:<12} {row['tests']:>6.0f} {row['wall_s']:>9.1f} {row['cpu_s']:>9.1f}")
    print(json.dumps(rows))
