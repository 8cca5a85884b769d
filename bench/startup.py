"""How long `python -m server` takes from process start to IDLE, and where the time goes.

Once, in a temporary directory: a fresh simulated cell is started and left to
commission itself (camera and robot calibration, the demo part), then stopped,
and its journal is replaced by one of `--rows` rows (default a million) built
through the journal's own records and commit chain (bench/journal_verify.py),
ending in IDLE. Then the server is started `--starts` times on that data
directory, as a plant restarts it, each time until its log says IDLE, and
stopped with SIGTERM.

Each start's phases are read from its log file (the cell logs each with its
time; the log's clock is the wall clock this benchmark starts the process on):

- `main`: process start to the first line of `main()` (the interpreter and the
  server's imports);
- `app built`: to the HTTP app built, lifespan starting (settings, logging,
  the routes);
- `journal check`: how long the journal's open took (PRAGMA quick_check and the
  digest chain's newest window, every table counted);
- `robot`, `glue`, `camera`: how long each device took to connect (the
  simulated camera: its first frame drawn in the image process);
- `port open`: process start to the HTTP port listening (every route prepared);
- `idle`: process start to the transition to IDLE (every device ready).

Target: IDLE under 1.5 s on a quiet machine.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import logging
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.cell_memory import admin, wait_state
from bench.journal_verify import build
from bench.report import emit
from tests.processes import ROOT, environment, server_process
from tests.serving import free_port

START_TIMEOUT_S = 120.0  # a bound on one start, never a performance assertion

MARKS = {  # phase: what its log line says
    "main": re.compile(r"__main__: logging to "),
    "app built": re.compile(r"uvicorn\.error: Waiting for application startup"),
    "port open": re.compile(r"uvicorn\.error: Uvicorn running on "),
    "idle": re.compile(r"INITIALIZING → IDLE"),
}
JOURNAL = re.compile(r"start-up: journal opened and checked in ([\d.]+) s")
DEVICES = re.compile(r"start-up: devices connected in (.*)$")
DEVICE = re.compile(r"(\w+) ([\d.]+) s")
STAMP = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d{3}) ")


def with_bytecode(env: dict[str, str]) -> dict[str, str]:
    """The environment without PYTHONDONTWRITEBYTECODE: an installed server runs from
    compiled bytecode (pip compiles what it installs; the first start here writes the
    rest), not from source compiled again at each start (0.7 s of it)."""
    return {name: value for name, value in env.items() if name != "PYTHONDONTWRITEBYTECODE"}


def commissioned(data: Path, settings: dict[str, str] | None = None) -> None:
    """A data directory as a simulated cell leaves it after its first start."""
    port = free_port()
    env = {**(settings or {}), "PYTHONDONTWRITEBYTECODE": ""}  # not set: bytecode written
    with server_process(port, data, env, timeout=600), admin(port, data) as api:
        wait_state(api, "IDLE", timeout=600)


def with_journal_of(data: Path, rows: int) -> int:
    """The data directory's journal replaced by one of `rows` rows; how many commits."""
    journal = data / "journal.db"
    for leftover in data.glob("journal.db*"):
        leftover.unlink()
    commits = build(journal, rows)
    os.chmod(journal, 0o600)
    return commits


def stamp(line: str) -> float | None:
    match = STAMP.match(line)
    if match is None:
        return None
    return datetime.datetime.strptime(match.group(1), "%Y-%m-%d %H:%M:%S.%f").timestamp()


def phases(log: str, started: float) -> dict[str, float]:
    """The phases of one start, in seconds, from its log (module docstring)."""
    found: dict[str, float] = {}
    for line in log.splitlines():
        at = stamp(line)
        if at is None:
            continue
        for phase, mark in MARKS.items():
            if phase not in found and mark.search(line):
                found[phase] = round(at - started, 3)
        if (journal := JOURNAL.search(line)) is not None:
            found["journal check"] = float(journal.group(1))
        if (devices := DEVICES.search(line)) is not None:
            for name, took in DEVICE.findall(devices.group(1)):
                found[name] = float(took)
    return found


def one_start(data: Path, settings: dict[str, str] | None = None) -> dict[str, float]:
    """Start the server on `data` until IDLE, stop it; its phases."""
    log_file = data / "logs" / "glue_cell.log"
    log_file.unlink(missing_ok=True)
    argv = [sys.executable, "-m", "server", "--port", str(free_port()), "--data-dir", str(data)]
    started = time.time()
    process = subprocess.Popen(
        argv,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env=with_bytecode(environment(settings)),
        cwd=ROOT,
    )
    try:
        deadline = time.monotonic() + START_TIMEOUT_S
        while True:
            text = log_file.read_text() if log_file.exists() else ""
            # Both lines: the cell can reach IDLE a moment before uvicorn logs its port.
            if MARKS["idle"].search(text) and MARKS["port open"].search(text):
                return phases(text, started)
            if process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"the server did not reach IDLE: {text[-2000:]}")
            time.sleep(0.02)
    finally:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(30)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(5)


def run(
    rows: int, starts: int, settings: dict[str, str] | None = None
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    directory = Path(tempfile.mkdtemp(prefix="bench-startup-"))
    try:
        data = directory / "data"
        data.mkdir()
        commissioned(data, settings)
        commits = with_journal_of(data, rows)
        samples = [one_start(data, settings) for _ in range(starts)]
    finally:
        shutil.rmtree(directory, ignore_errors=True)
    names = list(dict.fromkeys(name for sample in samples for name in sample))
    table = []
    for name in names:
        values = [sample[name] for sample in samples if name in sample]
        table.append(
            {
                "phase": name,
                "kind": "since process start" if name in MARKS else "duration",
                "median_s": round(statistics.median(values), 3),
                "min_s": round(min(values), 3),
                "max_s": round(max(values), 3),
                "n": len(values),
            }
        )
    return table, {"rows": commits * 3, "commits": commits, "starts": samples}


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--rows", type=int, default=1_000_000, help="rows in the journal")
    parser.add_argument("--starts", type=int, default=5, help="starts measured")
    parser.add_argument(
        "--setting",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="an environment variable for the measured starts, e.g. "
        "GLUE_APP_VISION_PROCESSING_TIMEOUT=30 on a busy machine",
    )
    args = parser.parse_args(argv)
    logging.disable(logging.ERROR)
    settings = dict(item.split("=", 1) for item in args.setting)
    rows, extra = run(args.rows, args.starts, settings)
    extra["settings"] = settings
    with contextlib.suppress(OSError):
        extra["load_average"] = os.getloadavg()
    emit("startup", rows, {"target_idle_s": 1.5, **extra})
    return rows


if __name__ == "__main__":
    main()
