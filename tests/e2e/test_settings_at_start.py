"""`glue-server` as a technician starts it with a wrong environment.

A bad value is one line naming the variable and what it accepts, exit 2, never
a traceback or a line naming the field but not the variable; a misspelt
GLUE_APP_ variable is a warning naming the closest setting, and the server
starts.
"""

from __future__ import annotations

import subprocess
import sys
from importlib import metadata

import httpx

from tests.processes import ROOT, _env, server_process
from tests.serving import free_port


def _run(*args: str, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "server", *args],
        capture_output=True,
        text=True,
        env=_env(env),
        cwd=ROOT,
        timeout=120,  # a hang guard, not a measure
    )


def test_a_bad_value_stops_the_start_with_one_line_and_exit_2(tmp_path) -> None:
    for variable, value, accepts in [
        ("GLUE_APP_SHIFT_HOURS", "abc", "shift_hours accepts a number 0.25 .. 744"),
        ("GLUE_APP_SAFE_POSITION", "400,0,200", "safe_position accepts a JSON list of 6"),
        # checked by the settings, not first by the log's set-up (a traceback, exit 1)
        ("GLUE_APP_LOG_ROTATION_SIZE", "abc", "log_rotation_size accepts a size such as 10MB"),
    ]:
        ran = _run("--port", str(free_port()), "--data-dir", str(tmp_path), env={variable: value})
        assert ran.returncode == 2, ran.stderr
        lines = ran.stderr.splitlines()
        assert len(lines) == 1, ran.stderr
        assert lines[0].startswith(f"glue-server: cannot start: {variable}={value!r}")
        assert accepts in lines[0]


def test_an_unknown_variable_is_a_warning_and_the_server_starts(tmp_path) -> None:
    port = free_port()
    env = {"GLUE_APP_SHIFT_HOUR": "12", "GLUE_APP_COMMISSION_SIMULATED_CELL": "false"}
    with server_process(port, tmp_path, env=env):
        assert httpx.get(f"http://127.0.0.1:{port}/health", timeout=5).status_code == 200
    log = (tmp_path / "server.log").read_text()
    assert (
        "GLUE_APP_SHIFT_HOUR names no setting and is ignored; did you mean GLUE_APP_SHIFT_HOURS?"
        in log
    )


def test_help_says_where_settings_come_from_and_version_is_the_packages() -> None:
    shown = _run("--help", env={"COLUMNS": "80"})
    assert shown.returncode == 0
    for text in ("GLUE_APP_", "GLUE_APP_CONFIG_PATH", "docs/settings.md", ".env", "--version"):
        assert text in shown.stdout, text
    assert all(len(line) <= 80 for line in shown.stdout.splitlines())
    version = _run("--version", env={})
    assert version.stdout.strip() == f"glue-server {metadata.version('glue-cell-server')}"
