"""A slow disk delays the answers to commands, never the decisions or the stop.

The design (server/storage/journal/writer.py): a command is answered only once its
journal record is durable, but the worker hands records to the writer thread
and goes on, and the e-stop halts the devices before its event is even queued.
tests/integration/test_persistence.py checks that an answer implies a durable
record on a healthy disk. Here every commit of the real SQLite journal takes
50–200 ms, and at chosen moments the disk stalls outright until the test lets
it go, to show by the order of events, not by the clock, that:

* the worker keeps deciding (the state moves, on GET /state too) while none of
  those commands has been answered, and each answer comes after its commit;
* the e-stop reaches the robot and closes the glue valve while the journal
  cannot write, before the commit that records the stop;
* nothing acknowledged is lost, and the slow disk is met by group commit.

Only the writer's commit is slowed (its connection wrapped); the SQL, the
transactions and the file are SQLite's own.
"""

from __future__ import annotations

import asyncio
import random
import sqlite3
import threading
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest

import server.bootstrap.cell
from server.storage.journal import Journal
from tests.reliability._journal_checks import missing_events
from tests.rig import SPRAY_DEMO, Rig, open_rig

COMMIT_DELAY_S = (0.05, 0.2)  # each commit of the journal writer takes this long
SEED = 20261204
CLIENTS = 8  # bounded for CI: concurrent clients in the load test
COMMANDS_PER_CLIENT = 20  # bounded for CI
SETTLE_S = 15  # bound on what must happen while the disk stalls; never reached when sound


@dataclass(frozen=True)
class Commit:
    finished_at: float  # time.time() once SQLite returned from the commit
    event_ids: tuple[str, ...]


class SlowCommits:
    """The writer thread's SQLite connection, with every commit slowed down.

    While `journal.disk` is cleared the commit waits for it: a stalled disk.
    """

    def __init__(self, connection: sqlite3.Connection, journal: SlowJournal) -> None:
        self._connection = connection
        self._journal = journal
        self._events: list[str] = []

    def execute(self, sql: str, params: tuple[Any, ...] = ()) -> sqlite3.Cursor:
        if "INTO events " in sql:
            self._events.append(params[0])
        return self._connection.execute(sql, params)

    def __enter__(self) -> SlowCommits:
        self._connection.__enter__()
        return self

    def __exit__(self, *exc_info: Any) -> Any:
        self._journal.disk.wait()
        time.sleep(self._journal.rng.uniform(*COMMIT_DELAY_S))
        result = self._connection.__exit__(*exc_info)  # the commit (or the rollback)
        self._journal.commits.append(Commit(time.time(), tuple(self._events)))
        self._events.clear()
        return result

    def __getattr__(self, name: str) -> Any:
        return getattr(self._connection, name)


class SlowJournal(Journal):
    """The production journal on a slow disk that the test can also stall."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.commits: list[Commit] = []
        self.disk = threading.Event()
        self.disk.set()
        self.rng = random.Random(SEED)

    def _connect(self) -> sqlite3.Connection:
        return SlowCommits(super()._connect(), self)  # type: ignore[return-value]

    def commit_of(self, event_id: str) -> Commit:
        """The commit that made `event_id` durable."""
        return next(c for c in self.commits if event_id in c.event_ids)


@asynccontextmanager
async def slow_rig(data: Path, monkeypatch: pytest.MonkeyPatch) -> AsyncIterator[Rig]:
    monkeypatch.setattr(server.bootstrap.cell, "Journal", SlowJournal)
    async with open_rig(data) as rig:
        assert isinstance(rig.cell.journal, SlowJournal)
        yield rig


def journal_of(rig: Rig) -> SlowJournal:
    return rig.cell.journal  # type: ignore[return-value]


@asynccontextmanager
async def stalled(journal: SlowJournal) -> AsyncIterator[None]:
    """The disk writes nothing inside the block (it always resumes after)."""
    journal.disk.clear()
    try:
        yield
    finally:
        journal.disk.set()


@dataclass(frozen=True)
class Answer:
    status: int
    body: dict[str, Any]
    at: float  # time.time() when the answer arrived


async def post(rig: Rig, command: str, body: dict[str, Any] | None = None) -> Answer:
    response = await rig.api.post(f"/{command}", json=body)
    return Answer(response.status_code, response.json(), time.time())


async def until(predicate: Callable[[], bool], what: str) -> None:
    try:
        async with asyncio.timeout(SETTLE_S):
            while not predicate():
                await asyncio.sleep(0.002)
    except TimeoutError:
        raise AssertionError(f"while the disk stalled, never saw {what}") from None


def assert_answered_after_commit(journal: SlowJournal, answers: list[Answer]) -> None:
    for answer in answers:
        assert answer.status == 202, answer.body
        commit = journal.commit_of(answer.body["event_id"])
        assert commit.finished_at <= answer.at, (commit, answer)


async def test_the_worker_decides_while_the_disk_stalls(tmp_path, monkeypatch) -> None:
    async with slow_rig(tmp_path, monkeypatch) as rig:
        journal, worker = journal_of(rig), rig.cell.worker
        steps = [
            ("start", SPRAY_DEMO, "EXECUTING_TRAJECTORY"),
            ("pause", None, "PAUSED"),
            ("resume", None, "EXECUTING_TRAJECTORY"),
            ("cancel", None, "IDLE"),
        ]
        pending: list[asyncio.Task[Answer]] = []
        async with stalled(journal):
            for command, body, state in steps:
                pending.append(asyncio.create_task(post(rig, command, body)))
                await until(lambda s=state: worker.ctx.state.value == s, f"{command} decided")
                assert (await rig.state())["state"] == state
            assert not any(task.done() for task in pending), "answered before it was durable"
        answers = list(await asyncio.gather(*pending))

        assert_answered_after_commit(journal, answers)
        ids = [answer.body["event_id"] for answer in answers]
        decided = {r.event_id: r.timestamp for r in worker.ctx.history if r.event_id in ids}
        assert set(decided) == set(ids)
        # The last command was decided before the first one's record was on disk.
        assert max(decided.values()) < journal.commit_of(ids[0]).finished_at


async def test_the_estop_reaches_the_devices_while_the_disk_stalls(tmp_path, monkeypatch) -> None:
    async with slow_rig(tmp_path, monkeypatch) as rig:
        journal, robot, glue, worker = journal_of(rig), rig.robot, rig.glue, rig.cell.worker
        await rig.start_spraying()
        stops = robot.stop_received_count
        async with stalled(journal):
            estop = asyncio.create_task(post(rig, "estop", {"reason": "slow disk"}))
            await until(lambda: robot.stop_received_count > stops, "the robot's stop")
            await until(lambda: not glue.valve_open, "the valve closed")
            await until(lambda: worker.ctx.state.value == "ERROR", "ERROR decided")
            stopped_at, closed_at = robot.last_stop_at, glue.close_commanded_at
            assert not estop.done(), "answered before it was durable"
        answer = await estop

        assert answer.status == 202 and answer.body["state"] == "ERROR", answer.body
        commit = journal.commit_of(answer.body["event_id"])
        assert stopped_at is not None and closed_at is not None
        assert stopped_at < commit.finished_at and closed_at < commit.finished_at
        assert commit.finished_at <= answer.at
        assert (await rig.reset()).status_code == 202
        await rig.wait_state("IDLE")


MIX = [("start", SPRAY_DEMO), ("pause", None), ("resume", None), ("cancel", None), ("reset", None)]


async def load(rig: Rig, seed: int) -> list[Answer]:
    """One client's commands, each sent once the last is answered; an e-stop now and then."""
    rng = random.Random(seed)
    answers = []
    async with httpx.AsyncClient(
        base_url=rig.api.base_url, headers=rig.api.headers, timeout=30
    ) as http:
        for _ in range(COMMANDS_PER_CLIENT):
            command, body = ("estop", None) if rng.random() < 0.05 else rng.choice(MIX)
            response = await http.post(f"/{command}", json=body)
            answers.append(Answer(response.status_code, response.json(), time.time()))
    return answers


async def test_nothing_acknowledged_is_lost_on_a_slow_disk(tmp_path, monkeypatch) -> None:
    async with slow_rig(tmp_path, monkeypatch) as rig:
        journal = journal_of(rig)
        batches = await asyncio.gather(*(load(rig, SEED + n) for n in range(CLIENTS)))
        answers = [answer for batch in batches for answer in batch]
        path = journal.path

        assert {a.status for a in answers} <= {202, 409}, {a.status for a in answers}
        for answer in answers:
            assert journal.commit_of(answer.body["event_id"]).finished_at <= answer.at
        # The slow disk is met by group commit: commits carry several events at once.
        largest = max(len(commit.event_ids) for commit in journal.commits)
        print(
            f"slow disk: {len(answers)} commands, {len(journal.commits)} commits, up to {largest}"
        )
        assert largest > 1
    acknowledged = {answer.body["event_id"] for answer in answers}
    assert missing_events(path, acknowledged) == set()
