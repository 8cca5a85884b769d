"""`gluectl line` against Debian's mosquitto, fed the topic contract's messages by paho
stand-ins for three cells (tests/line_publisher.py); gluectl runs as a process."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from server.line.broker import BrokerPorts
from tests.line_broker_fixture import running_broker
from tests.line_publisher import publish_cell, state_message
from tests.processes import ROOT, environment, run_module, stop
from tests.serving import free_port


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[BrokerPorts]:
    with running_broker(tmp_path / "broker") as ports:
        yield ports


def three_cells(port: int) -> None:
    run = {"run_id": "r-1", "workpiece_id": "wp-7"}
    publish_cell(port, "cell-1", state_message("cell-1", "EXECUTING_TRAJECTORY", **run), 0.75)
    stopped = {"code": "ESTOP", "message": "stop pressed at the cell"}
    publish_cell(port, "cell-2", state_message("cell-2", "ERROR", stop_reason=stopped), None)
    publish_cell(port, "cell-3", state_message("cell-3", "IDLE"), 0.5)


def gluectl_line(*args: str) -> subprocess.CompletedProcess[str]:
    return run_module("clients.gluectl", "line", *args, timeout=60)


def test_once_json_lists_every_cell_as_the_broker_holds_it(broker: BrokerPorts) -> None:
    three_cells(broker.mqtt)
    answer = gluectl_line("--broker", broker.login_url("line-view"), "--once", "--json")
    assert answer.returncode == 0, answer.stderr
    cells = {row["cell_id"]: row for row in json.loads(answer.stdout)["cells"]}
    assert list(cells) == ["cell-1", "cell-2", "cell-3"]
    assert cells["cell-1"]["state"] == "EXECUTING_TRAJECTORY" and cells["cell-1"]["oee"] == 0.75
    assert cells["cell-1"]["run_id"] == "r-1" and cells["cell-1"]["workpiece_id"] == "wp-7"
    reason = cells["cell-2"]["stop_reason"]
    assert reason == {"code": "ESTOP", "message": "stop pressed at the cell"}
    assert cells["cell-2"]["oee"] is None
    assert all(row["online"] is True for row in cells.values())
    table = gluectl_line("--broker", broker.login_url("line-view"), "--once")
    assert table.returncode == 0, table.stderr
    assert "ESTOP: stop pressed at the cell" in table.stdout and "75.0 %" in table.stdout


def test_a_cell_that_dies_reads_offline(broker: BrokerPorts) -> None:
    """The stand-in holds its connection with a last will, then is killed (-9)."""
    port = str(broker.mqtt)
    cell = subprocess.Popen(
        [sys.executable, "-m", "tests.line_publisher", "--cell", "cell-9", "--port", port],
        stdout=subprocess.PIPE,
        text=True,
        env=environment(),
        cwd=ROOT,
    )
    try:
        assert cell.stdout is not None and cell.stdout.readline().strip() == "published"
        before = json.loads(
            gluectl_line("--broker", broker.login_url("line-view"), "--once", "--json").stdout
        )
        assert [(c["cell_id"], c["online"]) for c in before["cells"]] == [("cell-9", True)]
        os.kill(cell.pid, signal.SIGKILL)
        cell.wait()
        after = json.loads(
            gluectl_line("--broker", broker.login_url("line-view"), "--once", "--json").stdout
        )
        assert [(c["cell_id"], c["online"]) for c in after["cells"]] == [("cell-9", False)]
    finally:
        stop(cell)


def test_live_json_prints_a_document_per_change_with_the_runs_progress(
    broker: BrokerPorts,
) -> None:
    three_cells(broker.mqtt)
    watcher = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "clients.gluectl",
            "line",
            "--broker",
            broker.login_url("line-view"),
            "--json",
        ],
        stdout=subprocess.PIPE,
        text=True,
        env=environment(),
        cwd=ROOT,
    )
    try:
        assert watcher.stdout is not None
        first: dict[str, Any] = json.loads(watcher.stdout.readline())
        assert len(first["cells"]) == 3
        progress = {"run_id": "r-1", "waypoint": 4, "total": 10, "fraction": 0.4}
        run = {"run_id": "r-1"}
        state = state_message("cell-1", "EXECUTING_TRAJECTORY", **run)
        publish_cell(broker.mqtt, "cell-1", state, 0.75, progress)
        while True:  # each message is one more document; the progress comes last
            document = json.loads(watcher.stdout.readline())
            cell_1 = document["cells"][0]
            if cell_1["progress"] is not None:
                break
        assert cell_1["progress"] == {"cell_id": "cell-1", **progress}
    finally:
        stop(watcher)


def test_an_unreachable_broker_exits_5() -> None:
    answer = gluectl_line("--broker", f"mqtt://127.0.0.1:{free_port()}", "--once", "--json")
    assert answer.returncode == 5
    assert json.loads(answer.stdout)["error"] == "Unreachable"
    bad = gluectl_line("--broker", "http://nowhere", "--once")
    assert bad.returncode == 2 and "not a broker address" in bad.stderr
