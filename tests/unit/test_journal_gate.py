"""A command is on record before it is answered, and not decided while the journal fails.

The worker runs on fakes with a real SQLite journal; a failed write is a real one
(a statement SQLite refuses), which sets the journal's `last_error` exactly as a
full disk does. The full disk itself is tests/reliability/test_full_disk.py.
"""

from __future__ import annotations

import asyncio
import sqlite3
from pathlib import Path

import pytest

from server.commands.answers import status_of as _status
from server.core.machine.events import AuditNote, Outcome
from server.core.machine.transitions import Event, State
from server.security.tokens import Role, TokenStore
from server.storage.journal import Record
from tests.conftest import START_PAYLOAD


def label(outcome: Outcome) -> str:
    return "accepted" if outcome.accepted else "refused"


NOTE = AuditNote("maint (maintenance, token t1)", "10.0.0.5", "POST /home", label)


async def fail_a_write(worker) -> None:
    """Make the journal's last write a failed one.

    The writer commits whatever is queued in one transaction, so the failing
    statement must not share it with the start-up's own records (their commit
    would fail too and fault the cell): everything queued before is written first.
    """
    await worker.recorder.journal.caught_up()
    failed = worker.recorder.journal.append([Record("INSERT INTO no_such_table VALUES (1)", ())])
    with pytest.raises(sqlite3.OperationalError):
        await failed
    assert worker.recorder.write_problem is not None


async def test_a_commands_audit_row_is_committed_with_its_event(make_worker) -> None:
    worker = await make_worker()
    outcome = await worker.request(Event.HOME_REQUESTED, source="api:10.0.0.5", audit=NOTE)
    # Answered once committed: the row is in the file, read without waiting for the writer.
    rows = await asyncio.to_thread(worker.recorder.journal.query, "audit")
    assert [(r["principal"], r["address"], r["action"], r["outcome"]) for r in rows] == [
        ("maint (maintenance, token t1)", "10.0.0.5", "POST /home", "accepted")
    ]
    assert rows[0]["detail"] == f"event {outcome.event_id}: {outcome.message}"


async def test_an_event_without_a_sender_writes_no_audit_row(make_worker) -> None:
    worker = await make_worker()
    await worker.request(Event.HOME_REQUESTED, source="facade")
    assert await asyncio.to_thread(worker.recorder.journal.query, "audit") == []


async def test_a_command_queued_while_the_journal_fails_is_refused_unchanged(make_worker) -> None:
    worker = await make_worker()
    await fail_a_write(worker)
    envelope = worker.submit(Event.START_REQUESTED, source="api", payload=START_PAYLOAD)
    assert envelope.future is not None
    outcome = await envelope.future
    assert not outcome.accepted and outcome.journal_problem is not None
    assert "journal cannot write" in outcome.message
    assert worker.ctx.state is State.IDLE and worker.ctx.operation is None


async def test_a_command_asks_the_journal_with_a_real_write_and_goes_once_it_writes(
    make_worker,
) -> None:
    worker = await make_worker()
    await fail_a_write(worker)
    outcome = await worker.request(Event.HOME_REQUESTED, source="api")
    assert outcome.accepted and outcome.journal_problem is None
    assert worker.recorder.write_problem is None


async def test_the_estop_is_not_held_by_a_failing_journal(make_worker) -> None:
    worker = await make_worker()
    await fail_a_write(worker)
    outcome = await worker.stops.stop(source="api")
    assert outcome.accepted and worker.ctx.state is State.ERROR
    assert worker.devices.glue.valve_open is False


def outcome(event: Event, accepted: bool, problem: str | None = None) -> Outcome:
    return Outcome(accepted, "e-1", event, State.ERROR, "m", journal_problem=problem)


def test_no_command_that_is_not_on_record_is_answered_202_but_the_stop() -> None:
    assert _status(outcome(Event.START_REQUESTED, True)) == 202
    assert _status(outcome(Event.START_REQUESTED, True, "disk full")) == 503
    assert _status(outcome(Event.RESET_REQUESTED, False, "disk full")) == 503
    assert _status(outcome(Event.PAUSE_REQUESTED, False)) == 409
    # The stop has halted the cell whether or not the journal could record it.
    assert _status(outcome(Event.EMERGENCY_STOP, True, "disk full")) == 202


def test_not_journaled_keeps_the_decision_and_notes_it_once() -> None:
    decided = outcome(Event.START_REQUESTED, True)
    marked = decided.not_journaled("disk full").not_journaled("again")
    assert marked.accepted and marked.journal_problem == "disk full"
    assert marked.message == "m (not journaled: disk full)"


def test_a_revocation_that_cannot_be_saved_is_not_applied(tmp_path: Path) -> None:
    store = TokenStore(tmp_path)
    entry, token = store.create("line", Role.OPERATOR)
    # A real failed save: the file's place is taken by a directory the rename cannot replace.
    store.path.unlink()
    store.path.mkdir()
    (store.path / "keep").write_text("x")
    with pytest.raises(OSError):
        store.revoke(entry.id)
    assert store.verify(token) is not None
    assert store.get(entry.id).revoked_at is None
    with pytest.raises(OSError):
        store.add(store.mint("late", Role.VIEWER)[0])
    assert [e["name"] for e in store.list()] == ["line"]
