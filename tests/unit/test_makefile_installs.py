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


def recipe(target: str) -> str:
    """The Makefile's recipe of `target`: its rule line to the next blank line."""
    text = (ROOT / "Makefile").read_text()
    return text[text.index(f"\n{target}:") + 1 :].split("\n\n", 1)[0]


def test_the_deployment_tools_bring_no_container_engine() -> None:
    """`make test` validates compose files with Debian's docker-compose, whose recommends
    are docker.io, containerd and iptables: a container engine and its services on the
    developer's machine. The install leaves recommends out."""
    install = recipe("deploy-tools").split("$(APT_INSTALL)", 1)[1]
    assert "--no-install-recommends" in install and "docker-compose" in install
    for engine in ("docker.io", "containerd", "iptables"):
        assert engine not in install


# The targets that install Debian packages, and what each installs.
APT_TARGETS = {
    "browser": "chromium",
    "node": "nodejs",
    "deploy-tools": "docker-compose systemd",
    "mosquitto": "mosquitto mosquitto-clients",
    "promtool": "prometheus",
}
INSTALLER = ROOT / "tools" / "apt-install-quiet"


def test_every_debian_install_goes_through_the_installer_that_changes_no_service(
    clone: Path,
) -> None:
    """Debian's mosquitto and prometheus start and enable their services on install
    (mosquitto's then holds port 1883, where `make line` starts its broker): each
    install target runs tools/apt-install-quiet, never apt-get install itself."""
    text = (ROOT / "Makefile").read_text()
    assert "APT_INSTALL := sh tools/apt-install-quiet" in text
    assert text.count("apt-get install") == 0, "an apt-get install outside the installer"
    make = shutil.which("make")
    assert make is not None
    for target, packages in APT_TARGETS.items():
        planned = subprocess.run(
            [make, "-n", target], cwd=clone, capture_output=True, text=True, check=True
        ).stdout
        command = " ".join(planned.replace("\\\n", " ").split())
        assert "sh tools/apt-install-quiet " in command, (target, command)
        installed = command.split("sh tools/apt-install-quiet ", 1)[1].split(";")[0].split()
        assert [word for word in installed if not word.startswith("-")] == packages.split()
    assert set(APT_TARGETS) <= set(recipe("test").split("\n", 1)[0].split())


FAKE_APT_GET = """#!/bin/sh
# apt-get as this test sees it: `install` does what mosquitto's maintainer scripts do,
# asking policy-rc.d before starting the service and enabling it for systemd and SysV.
echo "apt-get $*" >>"$FAKE_LOG"
[ "$1" = install ] || exit 0
if "$APT_QUIET_POLICY_RC_D" mosquitto start; then
    echo "mosquitto started" >>"$FAKE_LOG"
else
    echo "mosquitto start refused: $?" >>"$FAKE_LOG"
fi
mkdir -p "$APT_QUIET_UNIT_DIR/multi-user.target.wants" "$APT_QUIET_ETC/rc2.d"
ln -s /lib/systemd/system/mosquitto.service \
    "$APT_QUIET_UNIT_DIR/multi-user.target.wants/mosquitto.service"
ln -s ../init.d/mosquitto "$APT_QUIET_ETC/rc2.d/S01mosquitto"
exit "${FAKE_STATUS:-0}"
"""


def fake_system(tmp_path: Path) -> dict[str, str]:
    """A system with one service of the administrator's enabled (ssh), the paths the
    installer uses pointed at it, and the fake apt-get."""
    units, etc = tmp_path / "systemd", tmp_path / "etc"
    (units / "multi-user.target.wants").mkdir(parents=True)
    (units / "multi-user.target.wants" / "ssh.service").symlink_to("/lib/systemd/ssh.service")
    (etc / "rc2.d").mkdir(parents=True)
    (etc / "rc2.d" / "S01ssh").symlink_to("../init.d/ssh")
    apt_get = tmp_path / "apt-get"
    apt_get.write_text(FAKE_APT_GET)
    apt_get.chmod(0o755)
    return {
        "PATH": os.environ["PATH"],
        "APT_QUIET_POLICY_RC_D": str(tmp_path / "sbin" / "policy-rc.d"),
        "APT_QUIET_UNIT_DIR": str(units),
        "APT_QUIET_ETC": str(etc),
        "APT_QUIET_APT_GET": str(apt_get),
        "FAKE_LOG": str(tmp_path / "log"),
    }


def install_quietly(env: dict[str, str], *packages: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["sh", str(INSTALLER), *packages], env=env, capture_output=True, text=True, check=False
    )


def test_the_installer_starts_no_service_and_leaves_none_enabled(tmp_path: Path) -> None:
    env = fake_system(tmp_path)
    answer = install_quietly(env, "mosquitto", "mosquitto-clients")
    assert answer.returncode == 0, answer.stderr
    log = (tmp_path / "log").read_text().splitlines()
    assert log == [
        "apt-get update -qq",
        "apt-get install -y -qq mosquitto mosquitto-clients",
        "mosquitto start refused: 101",
    ]
    units, etc = Path(env["APT_QUIET_UNIT_DIR"]), Path(env["APT_QUIET_ETC"])
    assert sorted(p.name for p in (units / "multi-user.target.wants").iterdir()) == ["ssh.service"]
    assert sorted(p.name for p in (etc / "rc2.d").iterdir()) == ["K01mosquitto", "S01ssh"]
    assert not Path(env["APT_QUIET_POLICY_RC_D"]).exists()  # none before, none after
    assert "mosquitto.service disabled" in answer.stdout


def test_the_installer_puts_back_the_policy_it_found_even_when_apt_fails(
    tmp_path: Path,
) -> None:
    env = fake_system(tmp_path)
    policy = Path(env["APT_QUIET_POLICY_RC_D"])
    policy.parent.mkdir()
    policy.write_text("#!/bin/sh\n# the administrator's policy\nexit 0\n")
    policy.chmod(0o750)
    answer = install_quietly(env | {"FAKE_STATUS": "100"}, "prometheus")
    assert answer.returncode == 100
    assert policy.read_text() == "#!/bin/sh\n# the administrator's policy\nexit 0\n"
    assert policy.stat().st_mode & 0o777 == 0o750
    assert "mosquitto start refused: 101" in (tmp_path / "log").read_text()
    assert not (
        Path(env["APT_QUIET_UNIT_DIR"]) / "multi-user.target.wants" / "mosquitto.service"
    ).exists()
