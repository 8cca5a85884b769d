"""Each make target installs only what it needs, once (Makefile: one stamp per set).

`make run` installs the server's dependencies only (about 310 MB), not the test and
bench extras (a 720 MB environment with Playwright and matplotlib). This asks the real
`make` what it would do (`make -n`) in a copy of the Makefile and the files its
stamps depend on, with the stamps placed as earlier targets would have left them;
nothing is installed.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

from tests.processes import ROOT

TEST_EXTRA = "-e '.[test]'"
BENCH_EXTRA = "-e '.[bench]'"


@pytest.fixture
def clone(tmp_path: Path) -> Path:
    for name in ("Makefile", "pyproject.toml", "constraints.txt"):
        shutil.copy(ROOT / name, tmp_path / name)
    os.utime(tmp_path / "pyproject.toml", (1_000_000, 1_000_000))
    os.utime(tmp_path / "constraints.txt", (1_000_000, 1_000_000))
    return tmp_path


def installs(directory: Path, target: str) -> list[str]:
    """What `make -n target` would install: each pip line's requirement."""
    make = shutil.which("make")
    assert make is not None, "make is needed to build and test this project"
    planned = subprocess.run(
        [make, "-n", target], cwd=directory, capture_output=True, text=True, check=True
    ).stdout
    return [
        line.split("constraints.txt ", 1)[1] for line in planned.splitlines() if " pip " in line
    ]


def leave_stamps(directory: Path, *names: str) -> None:
    """The venv and the stamps a target that already ran leaves (newer than their inputs)."""
    venv = directory / ".venv"
    (venv / "bin").mkdir(parents=True, exist_ok=True)
    (venv / "bin" / "python").touch()
    for name in names:
        stamp = venv / f".installed-{name}"
        stamp.touch()
        os.utime(stamp, (2_000_000, 2_000_000))


def test_run_installs_the_server_alone(clone: Path) -> None:
    assert installs(clone, "run") == ["-e ."]
    for target in ("diagram", "openapi"):
        assert installs(clone, target) == ["-e ."]


def test_each_target_adds_only_its_extras_once(clone: Path) -> None:
    assert installs(clone, "test") == ["-e .", TEST_EXTRA, BENCH_EXTRA]
    for target in ("test-fast", "test-loaded", "soak", "lint"):
        assert installs(clone, target) == ["-e .", TEST_EXTRA], target
    assert installs(clone, "bench") == ["-e .", BENCH_EXTRA]

    leave_stamps(clone, "run")  # after `make run`
    assert installs(clone, "run") == []
    assert installs(clone, "test") == [TEST_EXTRA, BENCH_EXTRA]
    assert installs(clone, "lint") == [TEST_EXTRA]

    leave_stamps(clone, "run", "test")  # after `make lint`
    assert installs(clone, "test") == [BENCH_EXTRA]
    assert installs(clone, "test-fast") == []

    leave_stamps(clone, "run", "test", "bench")
    assert installs(clone, "test") == [] and installs(clone, "bench") == []


def test_a_changed_pyproject_reinstalls_every_set_in_use(clone: Path) -> None:
    leave_stamps(clone, "run", "test", "bench")
    os.utime(clone / "pyproject.toml", (3_000_000, 3_000_000))
    assert installs(clone, "run") == ["-e ."]
    assert installs(clone, "test") == ["-e .", TEST_EXTRA, BENCH_EXTRA]


def test_the_deployment_tools_bring_no_container_engine() -> None:
    """`make test` validates compose files with Debian's docker-compose, whose recommends
    are docker.io, containerd and iptables: a container engine and its services on the
    developer's machine. The install leaves recommends out."""
    text = (ROOT / "Makefile").read_text()
    recipe = text[text.index("\ndeploy-tools:") :].split("\n\n", 1)[0]
    install = recipe[recipe.index("apt-get install") :]
    assert "--no-install-recommends" in install and "docker-compose" in install
    for engine in ("docker.io", "containerd", "iptables"):
        assert engine not in install
