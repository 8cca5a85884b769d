"""The README's "A whole cycle with curl" block, pasted as one block into bash against
`glue-server` on its own simulators, does what its comments say.

The block is read from README.md and run as written; the only change is the port
(`localhost:8000` becomes a free one, as tests run side by side). Its curl fails on
any 4xx (`--fail-with-body`), so the one refusal the block shows on purpose (the
409 of calibrate-robot while spraying) must be the only command that fails. An
`ERR` trap placed before it (not in it) names the line of each command that
failed.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import time
from pathlib import Path

import httpx

from tests.processes import ROOT, server_process
from tests.serving import admin_client, free_port

FAILED = re.compile(r"^FAILED\((\d+)\) at line (\d+)$", re.MULTILINE)
TRAP = "trap 'echo \"FAILED($?) at line $LINENO\" >&2' ERR\n"


def readme_block(heading: str) -> str:
    """The first ```sh block after `heading` in README.md."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    after = text[text.index(heading) :]
    match = re.search(r"```sh\n(.*?)```\n", after, re.DOTALL)
    assert match is not None, f"no sh block after {heading!r}"
    return match.group(1)


def wait_idle(client: httpx.Client, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while client.get("/state").json()["state"] != "IDLE":
        assert time.monotonic() < deadline, "the cell never reached IDLE"
        time.sleep(0.1)


def test_the_readme_curl_cycle_runs_as_pasted(tmp_path: Path) -> None:
    assert shutil.which("curl"), "the README's block needs curl"
    block = readme_block("## A whole cycle with curl")
    assert "localhost:8000" in block and "curl" in block
    port = free_port()
    script = TRAP + block.replace("localhost:8000", f"localhost:{port}")
    data = tmp_path / "data"  # the block reads data/admin.token, as after `make run`
    with server_process(port, data, log_path=tmp_path / "server.log"):
        client = admin_client(port, data)
        wait_idle(client)
        pasted = subprocess.run(
            ["bash"],
            input=script,
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=600,
        )
        out, err = pasted.stdout, pasted.stderr
        lines = script.splitlines()
        failed = [lines[int(line) - 1] for _, line in FAILED.findall(err)]
        assert len(failed) == 1 and "calibrate-robot   # 409" in failed[0], (failed, err)
        assert pasted.returncode == 0, err  # the last line: start allowed again

        assert '"message":"calibrate-robot is not allowed in EXECUTING_TRAJECTORY"' in out
        assert '"code":"EMERGENCY_STOP"' in out
        frame = (tmp_path / "frame.jpg").read_bytes()
        assert frame[:2] == b"\xff\xd8", "frame.jpg is not the run's JPEG"

        # The example workpiece was removed again: the library is what it was, so later
        # runs match the part as before.
        names = [w["id"] for w in client.get("/workpieces").json()["workpieces"]]
        assert names == ["demo"]
        # Every run the block started ran to its end; the cell is ready for the next.
        assert client.get("/state").json()["state"] == "IDLE"
        kinds = client.get("/operations").json()["operations"]
        assert {op["kind"] for op in kinds} >= {"trajectory", "calibrate_robot", "create_workpiece"}
