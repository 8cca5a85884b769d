"""The dashboard's canvas geometry (clients/hmi/geometry.js), tested in JavaScript with
node's own test runner (tests/unit/hmi/*.test.mjs) and run from here, so that
`pytest` covers it too. No npm, no packages: node alone.

A missing node fails, never skips: a green run must mean the geometry was tested.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
JS_TESTS = Path(__file__).resolve().parent / "hmi"
MIN_NODE = 18  # node:test and --test-reporter


def node() -> str:
    found = shutil.which("node")
    if found is None:
        pytest.fail(
            "node is missing: the dashboard's geometry tests (tests/unit/hmi/) run with "
            f"`node --test`; install Node.js {MIN_NODE} or newer (Debian: apt-get install nodejs).",
            pytrace=False,
        )
    version = subprocess.run([found, "--version"], capture_output=True, text=True, check=True)
    major = int(version.stdout.strip().lstrip("v").split(".")[0])
    if major < MIN_NODE:
        pytest.fail(f"node {version.stdout.strip()} is too old: the tests need {MIN_NODE}+")
    return found


def test_the_canvas_geometry_passes_its_node_tests() -> None:
    files = sorted(JS_TESTS.glob("*.test.mjs"))
    assert files, f"no JavaScript tests in {JS_TESTS}"
    run = subprocess.run(
        [node(), "--test", "--test-reporter=tap", *map(str, files)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    output = run.stdout + run.stderr
    assert run.returncode == 0, f"node --test failed:\n{output}"
    totals = {key: int(n) for key, n in re.findall(r"^# (\w+) (\d+)$", run.stdout, re.M)}
    assert totals.get("pass", 0) > 0, f"no test ran:\n{output}"
    assert totals.get("fail") == 0, output
    for untested in ("skipped", "todo", "cancelled"):
        assert totals.get(untested, 0) == 0, f"{totals[untested]} {untested}:\n{output}"
