"""A change's state snapshot is written once the change's commit is durable, never
beside it: its fsync would compete with the commit's, which every answer waits for."""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path

from server.core.machine.events import Outcome, payload_of
from server.core.machine.transitions import Event, State
from server.core.worker.context import MachineContext
from server.core.worker.event_queue import Envelope, Priority
from server.core.worker.recorder import Recorder
from server.core.worker.snapshot import SnapshotFile


class HeldJournal:
    """Takes the commit and reports it durable only when the test says so."""

    backlog = 0
    last_error = None
    damage = ()

    def __init__(self, durable: asyncio.Future[None]) -> None:
        self.durable = durable

    def append(self, records, *, durable=True):
        return self.durable


def written(path: Path) -> dict:
    deadline = time.monotonic() + 10  # a hang guard, not a measure
    while not path.exists():
        assert time.monotonic() < deadline, "the snapshot was never written"
        time.sleep(0.01)
    return json.loads(path.read_text())


def decide_a_stop(recorder: Recorder) -> tuple[Envelope, Outcome]:
    """An e-stop's change as the worker makes it: its snapshot, its commit, its answer."""
    event = Event.EMERGENCY_STOP
    future = asyncio.get_running_loop().create_future()
    envelope = Envelope(
        "e-1", event, "test", payload_of(event, None), Priority.EMERGENCY, future=future
    )
    outcome = Outcome(True, "e-1", event, State.ERROR, "stopped")
    recorder.save_snapshot({"state": "ERROR", "since": 1.0}, None)
    recorder.answer_when_durable(envelope, outcome, recorder.commit(envelope, outcome))
    return envelope, outcome


async def test_the_snapshot_waits_for_its_changes_commit(tmp_path: Path) -> None:
    durable: asyncio.Future[None] = asyncio.get_running_loop().create_future()
    path = tmp_path / "state.json"
    snapshot_file = SnapshotFile(path, interval=3600)
    snapshot_file.start()
    recorder = Recorder(HeldJournal(durable), lambda _: None, MachineContext(10), snapshot_file)
    envelope, outcome = decide_a_stop(recorder)
    await asyncio.sleep(0.3)  # time enough for the writer thread, had it been handed over
    assert not path.exists()
    durable.set_result(None)
    assert (await asyncio.to_thread(written, path))["state"] == "ERROR"
    assert envelope.future.result() is outcome
    snapshot_file.stop()


async def test_the_snapshot_follows_the_answer(tmp_path: Path) -> None:
    """Its writer thread is woken a turn of the loop after the sender's answer, so the
    sender's task writes the answer before that thread can take the interpreter."""
    durable: asyncio.Future[None] = asyncio.get_running_loop().create_future()
    snapshot_file = SnapshotFile(tmp_path / "state.json", interval=3600)
    order: list[str] = []
    snapshot_file.save = lambda copy: order.append("snapshot handed over")  # type: ignore[method-assign]
    recorder = Recorder(HeldJournal(durable), lambda _: None, MachineContext(10), snapshot_file)
    envelope, _ = decide_a_stop(recorder)

    async def sender() -> None:
        await envelope.future
        order.append("answer written")

    answering = asyncio.ensure_future(sender())
    await asyncio.sleep(0)  # the sender waits for its answer
    durable.set_result(None)
    await answering
    for _ in range(5):
        await asyncio.sleep(0)
    assert order == ["answer written", "snapshot handed over"]
