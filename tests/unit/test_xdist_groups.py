"""`make test`'s grouping (tests/xdist_groups.py): under `pytest-xdist --dist loadgroup`, a
module with a module-scoped fixture sets it up once, on one worker, and still runs
every test; ungrouped tests still run on either worker; tests that a plugin
gave one id between them (as schemathesis does, one per API operation) each run.

Runs pytest with two workers (child processes over pipes, no sockets) on a generated
suite whose fixture records each set-up.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from tests.processes import environment

SHARED = """
import os
import pytest

SETUPS = {setups!r}


@pytest.fixture(scope="module")
def shared():
    with open(SETUPS, "a") as out:
        out.write(os.environ.get("PYTEST_XDIST_WORKER", "none") + "\\n")
    return 1


@pytest.mark.parametrize("n", range(8))
def test_reads_the_shared_fixture(shared, n):
    assert shared == 1
"""

ALONE = """
import os
import pytest

RUNS = {runs!r}


@pytest.mark.parametrize("n", range(8))
def test_alone(n):
    with open(RUNS, "a") as out:
        out.write(os.environ["PYTEST_XDIST_WORKER"] + "\\n")
"""


# Four tests from a file of cases, all with the same id, as schemathesis's tests of one
# function are under the pinned pytest.
ONE_ID = """
import pytest

RUNS = {runs!r}


class Case(pytest.Item):
    def runtest(self):
        with open(RUNS, "a") as out:
            out.write(self.name + "\\n")


class Cases(pytest.File):
    def collect(self):
        for line in self.path.read_text().split():
            yield Case.from_parent(self, name=f"case[{{line}}]", nodeid=f"{{self.nodeid}}::case")


def pytest_collect_file(parent, file_path):
    if file_path.suffix == ".cases":
        return Cases.from_parent(parent, path=file_path)
"""


def _run_pytest_on(suite: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [
            *(sys.executable, "-m", "pytest", "-v", "-p", "xdist", "-p", "tests.xdist_groups"),
            *("-n", "2", "--dist", "loadgroup", "-p", "no:cacheprovider"),
            *("--rootdir", str(suite), "-c", "/dev/null", str(suite)),
        ],
        capture_output=True,
        text=True,
        # Only xdist and the plugin: the other installed plugins' imports, in three processes,
        # would be most of this test's time.
        env=environment({"PYTEST_DISABLE_PLUGIN_AUTOLOAD": "1"}),
        cwd=Path(__file__).resolve().parents[2],
        timeout=300,
    )


def test_a_module_fixture_is_set_up_once_and_every_test_runs(tmp_path: Path) -> None:
    suite = tmp_path / "suite"
    suite.mkdir()
    setups, runs = tmp_path / "setups.txt", tmp_path / "runs.txt"
    (suite / "test_shared.py").write_text(SHARED.format(setups=str(setups)))
    (suite / "test_alone.py").write_text(ALONE.format(runs=str(runs)))
    done = _run_pytest_on(suite)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "16 passed" in done.stdout, done.stdout
    assert len(setups.read_text().split()) == 1, setups.read_text()
    # The scheduler saw the group: each shared test's id carries it.
    lines = done.stdout.splitlines()
    grouped = [line.rstrip() for line in lines if "PASSED" in line and "test_shared.py::" in line]
    assert len(grouped) == 8, done.stdout
    assert all("]@test_shared.py" in line for line in grouped), done.stdout
    # Each ungrouped test ran once, on a worker (which one is pytest-xdist's choice).
    assert len(runs.read_text().split()) == 8, runs.read_text()
    assert set(runs.read_text().split()) <= {"gw0", "gw1"}, runs.read_text()


def test_tests_given_one_id_between_them_each_run(tmp_path: Path) -> None:
    suite = tmp_path / "suite"
    suite.mkdir()
    runs = tmp_path / "runs.txt"
    (suite / "conftest.py").write_text(ONE_ID.format(runs=str(runs)))
    (suite / "operations.cases").write_text("get post put delete")
    done = _run_pytest_on(suite)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "4 passed" in done.stdout, done.stdout
    assert sorted(runs.read_text().split()) == [
        "case[delete]",
        "case[get]",
        "case[post]",
        "case[put]",
    ]
