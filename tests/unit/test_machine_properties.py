"""Random event sequences through the real worker (on fakes): the table always holds.

A hypothesis stateful test: each step posts one event, lets the worker decide,
and checks that every transition recorded is a row of the table and that an
emergency stop always leaves the cell in ERROR.
"""

from __future__ import annotations

import asyncio
import itertools
import tempfile
from pathlib import Path

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, rule

from server.core.infra.bus import Bus
from server.core.machine.events import (
    CreateWorkpiecePayload,
    FaultPayload,
    Payload,
    RunCompletedPayload,
    RunFailedPayload,
)
from server.core.machine.transitions import TRANSITIONS, Event, State
from server.core.operations import default_operations
from server.core.worker.devices import CellDevices
from server.core.worker.event_queue import Priority
from server.core.worker.worker import Worker
from server.settings.model import Settings
from server.storage.journal import Journal
from tests.conftest import START_PAYLOAD, demo_stores
from tests.fakes import FakeCamera, FakeGlue, FakeRobot

EXTERNAL_EVENTS = [e for e in Event if e is not Event.EMERGENCY_STOP]
INJECTED: dict[Event, Payload] = {
    Event.START_REQUESTED: START_PAYLOAD,
    Event.CREATE_WORKPIECE_REQUESTED: CreateWorkpiecePayload(),
    Event.ERROR_OCCURRED: FaultPayload("TEST", "injected", "test"),
    Event.OPERATION_COMPLETED: RunCompletedPayload("any"),
    Event.OPERATION_FAILED: RunFailedPayload("any", "TEST", "injected", "test"),
}


class CellMachine(RuleBasedStateMachine):
    def __init__(self) -> None:
        super().__init__()
        self.loop = asyncio.new_event_loop()
        self.glue = FakeGlue()
        self.robot = FakeRobot(speed_factor=2000)
        config = Settings(emergency_stop_timeout=0.2, processing_timeout=5)
        devices = CellDevices(self.robot, self.glue, FakeCamera())
        self.directory = tempfile.TemporaryDirectory()
        stores = demo_stores(Path(self.directory.name))
        self.journal = Journal(Path(self.directory.name) / "journal.db")
        self.journal.open()
        self.journal.start(self.loop)
        self.worker = Worker(
            config, devices, default_operations(), Bus(), stores, journal=self.journal
        )
        self.loop.run_until_complete(self.worker.start())
        self.checked = 0

    def teardown(self) -> None:
        self.loop.run_until_complete(self.worker.stop())
        self.journal.stop()
        self.loop.close()
        self.directory.cleanup()

    def _settle(self, seconds: float = 0.0) -> None:
        self.loop.run_until_complete(asyncio.sleep(seconds))

    @rule(event=st.sampled_from(EXTERNAL_EVENTS), wait=st.sampled_from([0.0, 0.001, 0.01]))
    def post(self, event: Event, wait: float) -> None:
        envelope = self.worker.submit(
            event,
            source="property",
            priority=Priority.REQUEST,
            payload=INJECTED.get(event),
        )
        self.loop.run_until_complete(envelope.future)
        self._settle(wait)

    @rule()
    def emergency_stop(self) -> None:
        outcome = self.loop.run_until_complete(self.worker.stops.stop(source="property"))
        assert outcome.accepted
        assert self.worker.ctx.state is State.ERROR
        assert self.glue.valve_open is False

    @rule()
    def reset(self) -> None:
        self.loop.run_until_complete(self.worker.request(Event.RESET_REQUESTED, source="p"))

    @rule(wait=st.sampled_from([0.005, 0.02]))
    def let_time_pass(self, wait: float) -> None:
        self._settle(wait)

    @invariant()
    def every_recorded_transition_is_in_the_table(self) -> None:
        history = list(self.worker.ctx.history)
        for record in history[self.checked :]:
            row = TRANSITIONS[State(record.old_state)].get(Event(record.event))
            assert row is not None, f"{record.old_state} on {record.event} is not in the table"
            assert row.target.value == record.new_state
        for before, after in itertools.pairwise(history):
            assert before.new_state == after.old_state, "history must be one unbroken chain"
        self.checked = max(0, len(history) - 1)

    @invariant()
    def the_valve_is_closed_whenever_no_trajectory_runs(self) -> None:
        """Outside a run the valve is open only during a purge (an activity in IDLE)."""
        purging = self.worker.activities.purging
        if self.worker.ctx.state not in (State.EXECUTING_TRAJECTORY, State.PAUSED) and not purging:
            assert self.glue.valve_open is False


CellMachine.TestCase.settings = settings(
    max_examples=60,
    stateful_step_count=30,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)
TestCellMachine = CellMachine.TestCase
