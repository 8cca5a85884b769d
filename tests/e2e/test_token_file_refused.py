"""A server on a data directory whose tokens.json was edited wrongly refuses to start.

Started, it would answer 500 to every request with the damaged token, /estop
included. The process exits before serving, with one line naming the entry and
the field, and no traceback.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time

import httpx
import pytest

from tests.processes import ROOT, _env, stop
from tests.serving import free_port

ENTRY = {
    "id": "0a1b2c3d",
    "name": "line 2 HMI",
    "role": "operator",
    "secret_sha256": "0" * 64,
    "created_at": 1_700_000_000.0,
    "revoked_at": None,
}


def _start_and_wait_for_exit(data_dir) -> tuple[int, str]:
    """Run the server; its exit code and output. Serving at all is the failure."""
    port = free_port()
    process = subprocess.Popen(
        [sys.executable, "-m", "server", "--port", str(port), "--data-dir", str(data_dir)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=_env({"GLUE_APP_COMMISSION_SIMULATED_CELL": "false"}),
        cwd=ROOT,
    )
    try:
        deadline = time.monotonic() + 120  # a hang guard, not a measure
        with httpx.Client(timeout=1) as poller:  # one client (a new one loads the CA store)
            while process.poll() is None:
                assert time.monotonic() < deadline, "the server neither served nor exited"
                try:
                    poller.get(f"http://127.0.0.1:{port}/health")
                except httpx.HTTPError:
                    time.sleep(0.1)
                    continue
                pytest.fail("the server started serving on a tokens.json it cannot read")
        assert process.stdout is not None
        return process.returncode, process.stdout.read()
    finally:
        stop(process)


@pytest.mark.parametrize(
    ("entry", "named"),
    [
        ({**ENTRY, "role": "superuser"}, "role"),
        ({k: v for k, v in ENTRY.items() if k != "created_at"}, "created_at"),
        ({**ENTRY, "created_at": "yesterday"}, "created_at"),
    ],
    ids=["unknown role", "missing field", "wrong type"],
)
def test_a_bad_token_entry_stops_the_start_naming_it(tmp_path, entry, named) -> None:
    (tmp_path / "tokens.json").write_text(json.dumps({"tokens": [entry]}), encoding="utf-8")
    code, output = _start_and_wait_for_exit(tmp_path)
    assert code != 0
    assert "Traceback" not in output
    [line] = [line for line in output.splitlines() if "cannot start" in line]
    assert "tokens.json" in line and "entry '0a1b2c3d'" in line and f"{named}:" in line
