"""Restarts: a damaged snapshot or journal never stops the cell from starting
safely, and a cell that stopped mid-operation comes back in ERROR saying where."""

from __future__ import annotations

import asyncio
import json
import logging
import sqlite3
import stat
import time
from pathlib import Path

import pytest

from server.bootstrap.cell import Cell
from server.core.machine.events import StopPayload
from server.core.machine.transitions import Command, State
from server.core.worker.devices import CellDevices
from server.settings.model import Settings
from server.storage.journal import Journal, records
from tests.conftest import START_PAYLOAD, demo_stores, wait_for_state
from tests.fakes import FakeCamera, FakeGlue, FakeRobot


def settings_for(data: Path, **overrides) -> Settings:
    return Settings(data_path=data, emergency_stop_timeout=0.5, **overrides)


async def started(data: Path, glue: FakeGlue | None = None, **overrides) -> Cell:
    demo_stores(data)
    cell = Cell(
        settings_for(data, **overrides),
        devices=CellDevices(FakeRobot(speed_factor=20), glue or FakeGlue(), FakeCamera()),
    )
    await cell.start()
    assert cell.worker is not None
    async with asyncio.timeout(10):
        while cell.worker.ctx.state is State.INITIALIZING:
            await asyncio.sleep(0.005)
    return cell


async def test_a_clean_restart_comes_up_idle_with_the_journal_kept(tmp_path) -> None:
    cell = await started(tmp_path)
    outcome = await cell.command(Command.START, source="test", payload=START_PAYLOAD)
    await wait_for_state(cell.worker, State.IDLE)
    await cell.stop()
    cell = await started(tmp_path)
    assert cell.worker.ctx.state is State.IDLE
    rows = cell.journal.query("events", filters={"type": "START_REQUESTED"})
    assert [r["id"] for r in rows] == [outcome.event_id]
    await cell.stop()


async def test_stopping_mid_operation_restarts_in_error_with_the_waypoint(tmp_path) -> None:
    glue = FakeGlue()
    cell = await started(tmp_path, glue=glue)
    cell.worker.devices.robot.speed_factor = 1  # slow enough to stop it mid-path
    await cell.command(Command.START, source="test", payload=START_PAYLOAD)
    async with asyncio.timeout(10):
        while not (
            cell.worker.ctx.operation and cell.worker.ctx.operation.progress.get("waypoint")
        ):
            await asyncio.sleep(0.005)
    await asyncio.sleep(0.2)  # the progress reaches the journal (not waited for by design)
    await cell.stop()  # a shutdown during an operation is an interruption too
    glue = FakeGlue()
    glue.valve_open = True  # as if the valve had stayed open
    cell = await started(tmp_path, glue=glue)
    worker = cell.worker
    assert worker.ctx.state is State.ERROR
    reason = worker.ctx.stop_reason
    assert reason.code == "INTERRUPTED"
    assert reason.message.startswith("interrupted during EXECUTING_TRAJECTORY at waypoint ")
    assert " of 7 (run " in reason.message
    assert glue.valve_open is False  # ERROR's entry closed it
    assert worker.ctx.operation is None  # nothing resumed
    operations = cell.journal.query("operations")
    assert operations[0]["outcome"] == "interrupted"
    assert (await cell.command(Command.RESET, source="test")).state is State.IDLE
    await cell.stop()


async def test_a_corrupt_snapshot_is_kept_aside_and_the_cell_starts_safely(tmp_path) -> None:
    (tmp_path / "state.json").write_text('{"state": "EXECUTING_TRAJ')  # truncated
    cell = await started(tmp_path)
    assert cell.worker.ctx.state is State.IDLE
    assert list(tmp_path.glob("state.json.corrupt-*"))
    await cell.stop()


async def test_a_snapshot_saying_mid_operation_restarts_in_error(tmp_path) -> None:
    (tmp_path / "state.json").write_text(json.dumps({"state": "PAUSED", "saved_at": time.time()}))
    cell = await started(tmp_path)
    assert cell.worker.ctx.state is State.ERROR
    assert cell.worker.ctx.stop_reason.message.startswith("interrupted during PAUSED")
    await cell.stop()


async def test_a_corrupt_journal_is_kept_aside_and_a_new_one_started(tmp_path) -> None:
    (tmp_path / "journal.db").write_bytes(b"SQLite format 3\x00" + b"\xff" * 3000)
    cell = await started(tmp_path)
    assert cell.worker.ctx.state is State.IDLE
    assert list(tmp_path.glob("journal.db.corrupt-*"))
    outcome = await cell.command(Command.START, source="test", payload=START_PAYLOAD)
    assert cell.journal.query("events", filters={"type": "START_REQUESTED"})[0]["id"] == (
        outcome.event_id
    )
    with sqlite3.connect(tmp_path / "journal.db") as connection:
        assert connection.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    await cell.stop()


async def test_retention_prunes_old_rows(tmp_path) -> None:
    journal = Journal(tmp_path / "journal.db", retention_days=1)
    journal.open()
    journal.start(asyncio.get_running_loop())
    old, new = time.time() - 3 * 86_400, time.time()
    await journal.append(
        [
            records.event("old", old, "X", "t", {}, "accepted", "", "IDLE"),
            records.event("new", new, "X", "t", {}, "accepted", "", "IDLE"),
        ]
    )
    journal.stop()
    journal.open()  # retention runs at open (and daily)
    assert [row["id"] for row in journal.query("events")] == ["new"]


async def test_a_command_answers_only_once_its_event_is_on_disk(tmp_path) -> None:
    cell = await started(tmp_path, journal_synchronous="FULL")
    outcome = await cell.command(Command.CALIBRATE_ROBOT, source="test")
    # Read with a separate connection, right after the answer: the row is there.
    with sqlite3.connect(tmp_path / "journal.db") as connection:
        row = connection.execute(
            "SELECT outcome, state FROM events WHERE id = ?", (outcome.event_id,)
        ).fetchone()
    assert row == ("accepted", outcome.state.value)
    await cell.stop()


def assert_restarted_in_error(cell: Cell, reason: str) -> None:
    """The cell came back in ERROR saying it was in ERROR before, and why."""
    assert cell.worker.ctx.state is State.ERROR
    message = cell.worker.ctx.stop_reason.message
    assert message.startswith("the cell was in ERROR when the server stopped")
    assert reason in message


async def test_error_is_latched_across_a_restart(tmp_path) -> None:
    cell = await started(tmp_path)
    await cell.command(Command.ESTOP, source="test", payload=StopPayload("guard door"))
    await asyncio.sleep(0.1)  # the snapshot is written behind the state change
    await cell.stop()
    cell = await started(tmp_path)
    assert_restarted_in_error(cell, "guard door")
    await cell.stop()


async def test_a_snapshot_one_change_behind_the_journal_gives_way_to_it(tmp_path) -> None:
    """A server killed after a change's commit and before its snapshot's write (written
    after the change's answer) restarts as the journal says: a reset that was answered
    stays done, and so does an e-stop, with its reason."""
    snapshot = tmp_path / "state.json"
    cell = await started(tmp_path)
    await cell.command(Command.ESTOP, source="test", payload=StopPayload("guard door"))
    await asyncio.sleep(0.1)
    in_error = snapshot.read_text()
    assert json.loads(in_error)["state"] == "ERROR"
    assert (await cell.command(Command.RESET, source="test")).state is State.IDLE
    await cell.stop()
    snapshot.write_text(in_error)  # as if killed before the reset's snapshot was written
    cell = await started(tmp_path)
    assert cell.worker.ctx.state is State.IDLE
    await asyncio.sleep(0.1)
    idle = snapshot.read_text()
    await cell.command(Command.ESTOP, source="test", payload=StopPayload("guard door"))
    await cell.stop()
    snapshot.write_text(idle)  # as if killed before the e-stop's snapshot was written
    cell = await started(tmp_path)
    assert_restarted_in_error(cell, "guard door")
    await cell.stop()


async def test_text_sqlite_cannot_store_does_not_stop_the_journal(tmp_path) -> None:
    journal = Journal(tmp_path / "journal.db")
    journal.open()
    journal.start(asyncio.get_running_loop())
    await journal.append(
        [records.error(time.time(), "X", "bad \ud800 text", "robot", "critical", "e1", "ERROR")]
    )
    await journal.append([records.event("e2", time.time(), "X", "t", {}, "accepted", "", "IDLE")])
    assert journal.query("errors")[0]["message"] == "bad ? text"
    assert journal.query("events")[0]["id"] == "e2"
    journal.stop()


async def test_last_error_is_the_last_write_failure_until_a_write_succeeds(tmp_path) -> None:
    journal = Journal(tmp_path / "journal.db")
    journal.open()
    journal.start(asyncio.get_running_loop())
    assert journal.last_error is None
    before = time.time()
    await journal.append([records.operation_started("r1", "trajectory", before, {})])
    bad = records.Record("INSERT INTO operations (run_id) VALUES (?)", ("r2",))  # NOT NULLs
    with pytest.raises(sqlite3.IntegrityError):
        await journal.append([bad])
    failure = journal.last_error
    assert failure is not None and "NOT NULL" in failure.message
    assert before <= failure.at <= time.time()
    assert failure.as_dict() == {"message": failure.message, "at": failure.at}
    await journal.caught_up()  # nothing written: the failure stays the last word
    assert journal.last_error == failure
    await journal.append([records.event("e1", time.time(), "X", "t", {}, "accepted", "", "IDLE")])
    assert journal.last_error is None
    journal.stop()


async def test_caught_up_waits_for_every_batch_queued_before_it(tmp_path) -> None:
    """Read-your-writes without a transaction of its own: each wait ends once the
    batches queued before it are committed (durable or not), a wait cancelled on
    the way disturbs no other, and with nothing queued it ends at once."""
    journal = Journal(tmp_path / "journal.db")
    journal.open()
    journal.start(asyncio.get_running_loop())
    await journal.caught_up()  # nothing queued yet
    for n in range(20):
        journal.append(
            [records.operation_started(f"r{n}", "trajectory", time.time(), {})], durable=False
        )
        if n == 9:
            cancelled = asyncio.ensure_future(journal.caught_up())
            halfway = asyncio.ensure_future(journal.caught_up())
            await asyncio.sleep(0)
            cancelled.cancel()
    await journal.caught_up()
    assert len(journal.query("operations", limit=100)) == 20
    await halfway
    assert cancelled.cancelled()
    journal.stop()


async def test_restarting_in_error_again_and_again_keeps_the_first_fault_as_it_was(
    tmp_path,
) -> None:
    """Each restart in ERROR says so once: the reason does not grow by one level per restart."""
    cell = await started(tmp_path)
    await cell.command(Command.ESTOP, source="test", payload=StopPayload("guard door"))
    await asyncio.sleep(0.1)  # the snapshot is written behind the state change
    await cell.stop()
    messages = []
    for _ in range(3):
        cell = await started(tmp_path)
        assert cell.worker.ctx.state is State.ERROR
        messages.append(cell.worker.ctx.stop_reason.message)
        await asyncio.sleep(0.1)
        await cell.stop()
    assert messages[0].startswith("the cell was in ERROR when the server stopped")
    assert "guard door" in messages[0]
    assert messages[0].count("the cell was in ERROR") == 1
    assert messages[1] == messages[0] and messages[2] == messages[0], messages


async def test_a_looser_data_directory_is_tightened_at_start_and_said_so(tmp_path, caplog) -> None:
    """However the cell is started (here: embedded, no `python -m server`)."""
    data = tmp_path / "data"
    cell = await started(data)
    await cell.stop()
    loose = [data, data / "workpieces", data / "journal.db", data / "state.json"]
    (data / "journal.db-wal").write_bytes(b"")  # as a crash may leave them
    (data / "journal.db-shm").write_bytes(b"")
    loose += [data / "journal.db-wal", data / "journal.db-shm"]
    for path in loose:
        path.chmod(0o777 if path.is_dir() else 0o666)
    with caplog.at_level(logging.WARNING, logger="server.storage.permissions"):
        cell = await started(data)
    try:
        for path in loose:
            mode = stat.S_IMODE(path.stat().st_mode)
            assert mode == (0o700 if path.is_dir() else 0o600), (path, oct(mode))
        said = [r.getMessage() for r in caplog.records if "tightened" in r.getMessage()]
        assert len(said) == 1 and "journal.db 666 -> 600" in said[0], said
    finally:
        await cell.stop()


async def test_retention_prunes_old_recordings_and_reports_too(tmp_path) -> None:
    journal = Journal(tmp_path / "journal.db", retention_days=1)
    journal.open()
    journal.start(asyncio.get_running_loop())
    old, new = time.time() - 3 * 86_400, time.time()

    def sample(at: float, run_id: str) -> records.Record:
        return records.run_sample(time=at, run_id=run_id, valve_open=False)

    def report(at: float) -> records.Record:
        return records.report(
            time=at, kind="shift", window_start=at - 60, window_end=at, document={}
        )

    await journal.append([sample(old, "old"), sample(new, "new"), report(old), report(new)])
    journal.stop()
    journal.open()  # retention runs at open (and daily)
    assert [row["run_id"] for row in journal.query("run_samples")] == ["new"]
    assert [row["time"] for row in journal.query("reports")] == [new]
