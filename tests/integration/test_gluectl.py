"""gluectl as scripts run it: `python -m clients.gluectl ...` as a subprocess, against a
real server on loopback (the core on in-process fakes), checking output and exit codes.

The server runs in the test's event loop; the CLI runs as an asyncio subprocess, so
the loop keeps serving while a command waits for its answer.
"""

from __future__ import annotations

import asyncio
import json
import os
import sys
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from rich.console import Console

from clients import gluectl
from clients.client import (
    AsyncCellClient,
    Busy,
    CellError,
    CellFaulted,
    CommandResult,
    Forbidden,
    InvalidRequest,
    NotFound,
    Refused,
    ServerError,
    Unauthorized,
    Unreachable,
    WaitTimeout,
)
from clients.gluectl.exit_codes import exit_code
from clients.gluectl.watch import WatchView, message_line
from server.bootstrap.cell import Cell
from server.core.machine.transitions import Event
from server.core.worker.devices import CellDevices
from server.settings.model import Settings
from tests.conftest import demo_stores
from tests.fakes import FakeCamera, FakeGlue, FakeRobot
from tests.serving import free_port, serve

ROOT = Path(__file__).resolve().parents[2]


@dataclass
class Ran:
    code: int
    stdout: str
    stderr: str

    def json(self) -> object:
        return json.loads(self.stdout)


@dataclass
class Cli:
    """The CLI pointed at one running server."""

    url: str
    data_dir: Path
    cell: Cell
    client: AsyncCellClient

    async def __call__(self, *args: str, env: dict[str, str] | None = None) -> Ran:
        """Run gluectl with --url and --data-dir (so it reads the admin token file)."""
        return await gluectl_process(
            "--url", self.url, "--data-dir", str(self.data_dir), *args, env=env
        )


def clean_env(extra: dict[str, str] | None = None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("GLUE_CELL_", "GLUE_APP_"))}
    env.update({"PYTHONPATH": str(ROOT), "COLUMNS": "200", "PYTHONUNBUFFERED": "1"})
    env.update(extra or {})
    return env


async def spawn(*args: str, env: dict[str, str] | None = None) -> asyncio.subprocess.Process:
    return await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "clients.gluectl",
        *args,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
        env=clean_env(env),
        cwd=ROOT,
    )


async def finish(process: asyncio.subprocess.Process) -> Ran:
    async with asyncio.timeout(30):
        stdout, stderr = await process.communicate()
    assert process.returncode is not None
    return Ran(process.returncode, stdout.decode(), stderr.decode())


async def gluectl_process(*args: str, env: dict[str, str] | None = None) -> Ran:
    return await finish(await spawn(*args, env=env))


@pytest.fixture
async def cli(fast_settings: Settings) -> AsyncIterator[Cli]:
    demo_stores(fast_settings.data_path)
    cell = Cell(
        fast_settings, devices=CellDevices(FakeRobot(speed_factor=5), FakeGlue(), FakeCamera())
    )
    async with serve(cell) as url:
        token = (fast_settings.data_path / "admin.token").read_text().strip()
        async with AsyncCellClient(url, token) as client:
            await client.wait_for_state("IDLE", 10)
            yield Cli(url, fast_settings.data_path, cell, client)


# --- doing things --------------------------------------------------------------------


async def test_state_as_a_table_and_as_json(cli: Cli) -> None:
    table = await cli("state")
    assert table.code == 0, table.stderr
    assert "IDLE" in table.stdout and "may do" in table.stdout and "calibrate-robot" in table.stdout
    for args in (("--json", "state"), ("state", "--json")):
        as_json = await cli(*args)
        assert as_json.code == 0 and as_json.json()["state"] == "IDLE"  # type: ignore[index]


async def test_a_cycle_start_then_wait_for_idle(cli: Cli) -> None:
    started = await cli("start", "--workpiece", "demo", "--no-contour-matching")
    assert started.code == 0, started.stderr
    assert started.stdout.startswith("start accepted: IDLE → EXECUTING_TRAJECTORY  (event ")
    waited = await cli("wait", "idle", "--timeout", "20")
    assert (waited.code, waited.stdout.strip(), waited.stderr) == (0, "IDLE", "")
    latest = await cli("--json", "history", "--limit", "2")
    rows = latest.json()
    assert isinstance(rows, list) and len(rows) == 2
    assert (rows[0]["old_state"], rows[0]["new_state"]) == ("EXECUTING_TRAJECTORY", "IDLE")
    assert "OPERATION_COMPLETED" in (await cli("history")).stdout


async def test_commands_answer_in_json_and_refusals_exit_3_with_the_reason(cli: Cli) -> None:
    refused = await cli("pause")
    assert refused.code == 3 and refused.stdout == ""
    assert refused.stderr.strip() == "gluectl: refused: pause is not allowed in IDLE"
    refused_json = await cli("--json", "resume")
    assert refused_json.code == 3
    assert refused_json.json() == {
        "error": "Refused",
        "status_code": 409,
        "message": "resume is not allowed in IDLE",
        "accepted": False,
        "event_id": refused_json.json()["event_id"],  # type: ignore[index]
        "state": "IDLE",
    }
    stopped = await cli("--json", "estop", "--reason", "door open")
    assert stopped.code == 0
    assert stopped.json()["state"] == "ERROR" and stopped.json()["accepted"] is True  # type: ignore[index]
    assert "door open" in (await cli("state")).stdout
    reset = await cli("reset")
    assert reset.code == 0 and reset.stdout.startswith("reset accepted: ERROR → IDLE")


async def test_the_other_commands(cli: Cli) -> None:
    for args, text in (
        (("workpieces",), "demo"),
        (("kpis",), "oee.availability"),
        (("health",), "robot"),
        (("allowed", "calibrate-robot"), "calibrate-robot is allowed in IDLE"),
    ):
        ran = await cli(*args)
        assert ran.code == 0 and text in ran.stdout, (args, ran)
        assert (await cli("--json", *args)).json()
    not_allowed = await cli("allowed", "resume")
    assert (not_allowed.code, not_allowed.stdout.strip()) == (3, "resume is not allowed in IDLE")
    for command, state in (
        ("calibrate-camera", "CALIBRATING_CAMERA"),
        ("calibrate-robot", "CALIBRATING_ROBOT"),
    ):
        ran = await cli("--json", command)
        assert ran.code == 0 and ran.json()["state"] == state  # type: ignore[index]
        await settle(cli.client)
    # No robot calibration on the fake camera: refused up front (exit 3), saying what to do.
    created = await cli("create-workpiece", "--name", "bracket", "--id", "bracket")
    assert created.code == 3 and "run calibrate-robot first" in created.stderr
    cli.cell.devices.robot.speed_factor = 0.5  # a run of several seconds: no race with the CLI
    await cli.client.start(workpiece_id="demo", contour_matching=False)
    for command, state in (
        ("pause", "PAUSED"),
        ("resume", "EXECUTING_TRAJECTORY"),
        ("cancel", "IDLE"),
    ):
        ran = await cli(command)
        assert ran.code == 0, ran.stderr
        assert f"{command} accepted: " in ran.stdout and f"→ {state}  (event " in ran.stdout


async def settle(client: AsyncCellClient) -> None:
    """Let an operation end; reset if it failed (the fake camera sees a blank table)."""
    try:
        await client.wait_for_state("IDLE", 20)
    except CellFaulted:
        await client.reset()


# --- failing in the documented ways ---------------------------------------------------------


async def test_no_token_exits_4_and_says_where_it_looked(cli: Cli, tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    ran = await gluectl_process("--url", cli.url, "--data-dir", str(empty), "state")
    assert ran.code == 4
    assert "gluectl: unauthorized: authentication required" in ran.stderr
    assert f"admin.token in {empty}" in ran.stderr
    token = (cli.data_dir / "admin.token").read_text().strip()
    from_env = await gluectl_process(
        "--url", cli.url, "--data-dir", str(empty), "state", env={"GLUE_CELL_TOKEN": token}
    )
    assert from_env.code == 0 and "IDLE" in from_env.stdout


async def test_a_role_too_low_exits_4_naming_the_role(cli: Cli) -> None:
    viewer = (await cli.client._http.post("/tokens", json={"name": "hmi", "role": "viewer"})).json()
    ran = await cli("--token", viewer["token"], "start")
    assert ran.code == 4
    assert ran.stderr.strip() == "gluectl: forbidden: this needs the operator role; hmi has viewer"


async def test_an_unreachable_server_exits_5(tmp_path: Path) -> None:
    url = f"http://127.0.0.1:{free_port()}"
    ran = await gluectl_process("--url", url, "--token", "x", "--json", "state")
    assert ran.code == 5 and f"gluectl: unreachable: cannot reach {url}" in ran.stderr
    assert ran.json()["error"] == "Unreachable"  # type: ignore[index]
    watched = await gluectl_process("--url", url, "--token", "x", "watch", "--count", "1")
    assert watched.code == 5 and "unreachable" in watched.stderr


async def test_an_invalid_request_exits_6_naming_the_field(cli: Cli) -> None:
    ran = await cli("start", "--workpiece", "../etc/passwd")
    assert ran.code == 6 and "workpiece_id" in ran.stderr
    unknown = await cli("allowed", "fly")
    assert unknown.code == 6 and "known operations" in unknown.stderr


async def test_a_full_queue_exits_7(cli: Cli) -> None:
    worker = cli.cell.worker
    assert worker is not None
    worker._task.cancel()
    await asyncio.gather(worker._task, return_exceptions=True)
    try:
        for _ in range(worker.queue.capacity):
            worker.submit(Event.PAUSE_REQUESTED, source="test")
        ran = await cli("pause")
    finally:
        worker._task = asyncio.create_task(worker._run())
    assert ran.code == 7 and "queue is full" in ran.stderr and "retry after 1 s" in ran.stderr


async def test_wait_exits_8_on_timeout_9_in_error_and_2_for_an_unknown_state(cli: Cli) -> None:
    timed_out = await cli("wait", "PAUSED", "--timeout", "0.3")
    assert timed_out.code == 8
    assert "timed out after 0.3 s waiting for PAUSED; the cell is in IDLE" in timed_out.stderr
    await cli.client.estop()
    faulted = await cli("--json", "wait", "IDLE", "--timeout", "5")
    assert faulted.code == 9 and "the cell is in ERROR, waiting for IDLE" in faulted.stderr
    assert faulted.json()["error"] == "CellFaulted"  # type: ignore[index]
    through = await cli("wait", "IDLE", "--timeout", "0.3", "--no-fail-on-error")
    assert through.code == 8
    assert (await cli("wait", "ERROR", "--timeout", "1")).code == 0
    unknown = await cli("wait", "SPRAYING")
    assert unknown.code == 2 and "unknown state 'SPRAYING'" in unknown.stderr


# --- watch ---------------------------------------------------------------------------------


async def test_watch_json_prints_the_snapshot_then_messages_in_order(cli: Cli) -> None:
    watcher = await spawn(
        "--url", cli.url, "--data-dir", str(cli.data_dir), "watch", "--json", "--count", "4"
    )
    assert watcher.stdout is not None
    first = json.loads(await asyncio.wait_for(watcher.stdout.readline(), 20))
    assert first["type"] == "snapshot" and first["state"] == "IDLE"
    await cli.client.start(workpiece_id="demo", contour_matching=False)
    ran = await finish(watcher)
    assert ran.code == 0, ran.stderr
    rest = [json.loads(line) for line in ran.stdout.splitlines()]
    assert len(rest) == 3
    assert [m["seq"] for m in rest] == [first["seq"] + 1, first["seq"] + 2, first["seq"] + 3]
    assert rest[0]["type"] == "state_changed" and rest[0]["new_state"] == "EXECUTING_TRAJECTORY"


async def test_watch_piped_prints_one_line_per_message(cli: Cli) -> None:
    watcher = await spawn(
        "--url",
        cli.url,
        "--data-dir",
        str(cli.data_dir),
        "watch",
        "--count",
        "2",
        "--type",
        "state_changed",
    )
    assert watcher.stdout is not None
    first = (await asyncio.wait_for(watcher.stdout.readline(), 20)).decode()
    assert "snapshot" in first and "state IDLE" in first
    await cli.client.start(workpiece_id="demo", contour_matching=False)
    ran = await finish(watcher)
    assert ran.code == 0, ran.stderr
    assert "state_changed  IDLE → EXECUTING_TRAJECTORY  (START_REQUESTED" in ran.stdout


def test_the_live_view_shows_progress_timeline_and_resyncs() -> None:
    """The view as the server feeds it (shapes as on /ws), rendered off-terminal."""
    view = WatchView("http://cell")
    boot = {"timestamp": 1.0, "old_state": "INITIALIZING", "new_state": "IDLE"}
    view.update(
        {"type": "snapshot", "seq": 3, "state": "IDLE", "operation": None, "history": [boot]}
    )
    running = {"state": "EXECUTING_TRAJECTORY", "operation": None}  # as the transition has it
    view.update(
        {
            "type": "state_changed",
            "seq": 4,
            "time": 2.0,
            "old_state": "IDLE",
            "event": "START_REQUESTED",
            "new_state": "EXECUTING_TRAJECTORY",
            "snapshot": running,
        }
    )

    def progress(seq: int, waypoint: int) -> dict[str, object]:
        return {
            "type": "progress",
            "seq": seq,
            "operation": "trajectory",
            "run_id": "r1",
            "waypoint": waypoint,
            "total": 7,
            "fraction": waypoint / 7,
        }

    def screen() -> str:
        console = Console(record=True, width=120, force_terminal=False)
        console.print(view.render())
        return console.export_text()

    view.update(progress(5, 3))
    shown = screen()
    assert "state EXECUTING_TRAJECTORY" in shown and "trajectory" in shown
    assert "waypoint 3/7 (43%)" in shown and "START_REQUESTED" in shown and "INITIALIZING" in shown
    view.update(
        {"type": "snapshot", "seq": 12, "resumed": True, "missed": 6, **running, "history": []}
    )
    view.update(progress(13, 5))
    shown = screen()
    assert "reconnected: missed 6 message(s); resynced" in shown and "waypoint 5/7 (71%)" in shown
    assert view.received == 5 and view.seq == 13

    # A resume the server fills: the replayed transition joins the timeline once.
    history = [boot, {"timestamp": 3.0, "old_state": "EXECUTING_TRAJECTORY", "new_state": "IDLE"}]
    resumed = {"type": "snapshot", "seq": 15, "resumed": True, "missed": 0, "replayed": 2}
    view.update({**resumed, "state": "IDLE", "operation": None, "history": history})
    view.update(progress(14, 7))
    view.update(
        {
            "type": "state_changed",
            "seq": 15,
            "time": 3.0,
            "old_state": "EXECUTING_TRAJECTORY",
            "event": "OPERATION_COMPLETED",
            "new_state": "IDLE",
            "snapshot": {"state": "IDLE", "operation": None},
        }
    )
    shown = screen()
    assert "reconnected: 2 message(s) replayed, none missed" in shown and "state IDLE" in shown
    assert shown.count("OPERATION_COMPLETED") == 1 and "INITIALIZING" not in shown
    assert [row.get("event") for row in view.timeline] == ["OPERATION_COMPLETED"]
    assert "(resumed, 2 replayed, missed 0)" in message_line(resumed)


# --- exit codes and help -------------------------------------------------------------------


def test_every_client_error_has_its_documented_exit_code() -> None:
    result = CommandResult(False, None, "IDLE", "no", 409)
    cases = [
        (Refused(result), 3),
        (Unauthorized("x", status_code=401), 4),
        (Forbidden("x", status_code=403), 4),
        (Unreachable("x"), 5),
        (InvalidRequest("x"), 6),
        (NotFound("x", status_code=404), 6),
        (Busy("x"), 7),
        (WaitTimeout("x", None), 8),
        (CellFaulted("x", {"state": "ERROR"}), 9),
        (ServerError("x", status_code=500), 1),
        (CellError("x"), 1),
    ]
    assert [exit_code(error) for error, _ in cases] == [code for _, code in cases]


async def test_help_documents_the_exit_codes() -> None:
    ran = await gluectl_process("--help")
    assert ran.code == 0
    for text in ("Exit codes", "3 refused (409)", "5 unreachable", "7 busy (503)", "8 timeout"):
        assert text in ran.stdout
    assert gluectl.__doc__ and "8  timeout in `wait`" in gluectl.__doc__
    usage = await gluectl_process("--no-such-option")
    assert usage.code == 2


async def test_jog_and_marker_teach_list_apply(cli: Cli) -> None:
    """The robot (a fake here) jogs one step; its pose is taught as a marker and listed."""
    jogged = await cli("--json", "jog", "x", "--", "-5")
    assert jogged.code == 0, jogged.stderr
    assert jogged.json()["accepted"] is True  # type: ignore[index]
    too_far = await cli("jog", "z", "190")
    assert too_far.code != 0 and "jog_max_step_mm" in too_far.stderr
    taught = await cli("--json", "marker", "teach", "4")
    assert taught.code == 0, taught.stderr
    assert taught.json()["draft"][4]["how"] == "taught"  # type: ignore[index]
    listed = await cli("marker", "list")
    assert listed.code == 0 and "taught" in listed.stdout and "missing" in listed.stdout
    refused = await cli("marker", "apply")
    assert refused.code != 0 and "markers.0" in refused.stderr
