"""The worker's record keeping: what one event caused goes to the journal in one commit.

Why a separate piece: the worker decides, the recorder remembers. Each record
the handling of an event produces (the transition, the fault, a run started
or ended) is collected while the event is handled and committed together with
the event's own row; the sender is answered only once that commit is durable,
so an acknowledged command is never lost to a crash. Progress, retries and
warnings are written without waiting: they are not acknowledgements. The
state snapshot a restart reads (`snapshot.py`) is saved here too, on each
change, once that change is durable and answered.

The recorder speaks in the cell's terms (a transition, a fault, a run); the
SQL behind each record lives in storage (`server.storage.journal`).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import Any

from server.common.errors import JournalUnavailable
from server.core.infra.clock import SYSTEM_CLOCK, Clock
from server.core.machine.events import Outcome
from server.core.worker.context import (
    FaultRecord,
    MachineContext,
    RunningOperation,
    TransitionRecord,
)
from server.core.worker.event_queue import Envelope
from server.core.worker.snapshot import SnapshotFile
from server.drivers.base import DeviceFault
from server.storage.journal import Journal, Record, records

log = logging.getLogger(__name__)

BACKLOG_LIMIT = 10_000  # records waiting for the disk; beyond it new requests are refused


class Recorder:
    """Collects the records of the event being handled and commits them with it."""

    def __init__(
        self,
        journal: Journal,
        post_fault: Callable[[DeviceFault], None],
        ctx: MachineContext,
        snapshot_file: SnapshotFile | None = None,
        clock: Clock = SYSTEM_CLOCK,
    ) -> None:
        self.journal = journal
        self.snapshot_file = snapshot_file  # the state to show after a restart, if kept
        self._post_fault = post_fault  # a write that failed stops the cell
        self._ctx = ctx
        self._clock = clock
        self._pending: list[Record] = []
        self._snapshot: dict[str, Any] | None = None  # the change's, saved after its answer

    @property
    def behind(self) -> bool:
        """The disk is too far behind to take more requests (refuse, never drop)."""
        return self.journal.backlog > BACKLOG_LIMIT

    @property
    def write_problem(self) -> str | None:
        """Why the journal's last write failed, or None: while set, commands are refused."""
        failure = self.journal.last_error
        return failure.message if failure else None

    async def ensure_writable(self) -> None:
        """Raise JournalUnavailable unless the journal can write.

        Why a real write: while the last write failed, nothing else tells the cell
        that the disk has space again (the commands that would write are refused),
        so each command asks with one small durable write; it clears `write_problem`
        when it succeeds.
        """
        if self.journal.last_error is None:
            return
        written = self.journal.append([records.write_check(self._clock.time())])
        if written is None:  # the writer is not started: nothing to ask
            return
        try:
            await written
        except Exception as exc:
            raise JournalUnavailable(str(exc)) from exc

    def journal_health(self) -> dict[str, Any]:
        """The journal's figures for /health: the backlog, the last write failure, and
        the damage start-up found."""
        failure = self.journal.last_error
        return {
            "backlog": self.journal.backlog,
            "last_error": failure.message if failure else None,
            "last_error_at": failure.at if failure else None,
            "damage": [damage.as_dict() for damage in self.journal.damage],
        }

    # --- records committed with the event ----------------------------------

    def transition(self, record: TransitionRecord) -> None:
        self._pending.append(records.transition(record.as_dict()))

    def fault(self, fault: FaultRecord, state: str) -> None:
        self._pending.append(
            records.error(
                fault.time,
                fault.code,
                fault.message,
                fault.component,
                fault.classification,
                fault.event_id,
                state,
                fault.context,
                fault.trace,
            )
        )

    def run_started(self, run: RunningOperation) -> None:
        self._pending.append(
            records.operation_started(run.run_id, run.name, run.started_at, dict(run.params))
        )

    def run_ended(
        self,
        run_id: str,
        outcome: str,
        result: dict[str, Any] | None,
        error: str | None,
        parts: int,
        inspection: dict[str, Any] | None = None,
    ) -> None:
        at = self._clock.time()
        self._pending.append(records.operation_ended(run_id, at, outcome, result, error, parts))
        if inspection is not None:  # in the same commit: an inspected run always has its row
            self._pending.append(records.inspection(at, run_id, inspection))

    def save_snapshot(self, snapshot: dict[str, Any], running: RunningOperation | None) -> None:
        """The state after a change, for the next start to see where the cell was;
        written once the change is on record and its sender answered
        (`answer_when_durable`).

        Why after: written beside the commit, the snapshot's fsync would compete
        with the commit's own, and every answer, an e-stop's too, would wait for it."""
        if self.snapshot_file is None:
            return
        operation = running.as_dict() if running is not None else None
        saved = {**snapshot, "operation": operation, "saved_at": self._clock.time()}
        self._snapshot = SnapshotFile.copy(saved)

    # --- records written at once, not waited on ------------------------------

    def planned(self, run_id: str, workpieces: int) -> None:
        """A run's parts on record as it is planned: a run the server's stop cuts short
        (closed as interrupted at the next start) still counts them as failed."""
        self.journal.append([records.operation_planned(run_id, workpieces)], durable=False)

    def progress(self, run_id: str, progress: dict[str, Any]) -> None:
        self.journal.append([records.operation_progress(run_id, progress)], durable=False)

    def recovery(self, run_id: str, code: str, attempt: int, succeeded: bool) -> None:
        record = records.recovery(self._clock.time(), run_id, code, attempt, succeeded)
        self.journal.append([record], durable=False)

    def warning(self, code: str, message: str, component: str, event_id: str, state: str) -> None:
        record = records.error(
            self._clock.time(), code, message, component, "warning", event_id, state
        )
        self.journal.append([record], durable=False)

    # --- the event itself, and its answer ----------------------------------

    def commit(self, envelope: Envelope, outcome: Outcome) -> asyncio.Future[None] | None:
        """The event's row, its audit row and everything it caused, in one write; the
        future marks it durable (so no command is answered without who sent it on record).
        The event's and state's names by `str()`, a StrEnum's value without the enum's
        Python-level `value` property (every event reads them)."""
        pending, self._pending = self._pending, []
        note = envelope.audit
        if note is not None:
            detail = f"event {envelope.event_id}: {outcome.message}"
            row = records.audit(
                self._clock.time(),
                note.principal,
                note.address,
                note.action,
                note.label(outcome),
                detail,
            )
            pending.append(row)
        event = records.event(
            envelope.event_id,
            envelope.timestamp,
            str(envelope.event),
            envelope.source,
            envelope.payload.as_dict(),
            "accepted" if outcome.accepted else "refused",
            outcome.message,
            str(outcome.state),
        )
        return self.journal.append([event, *pending])

    def answer_when_durable(
        self, envelope: Envelope, outcome: Outcome, durable: asyncio.Future[None] | None
    ) -> None:
        """Answer the sender once the event is on disk (say so when it could not be
        written); then hand the change's state snapshot to its writer."""
        self._answer(envelope, outcome, durable)
        snapshot, self._snapshot = self._snapshot, None
        if snapshot is None or self.snapshot_file is None:
            return
        if durable is None:
            self.snapshot_file.save(snapshot)
            return
        # A turn of the loop after the answer's: the sender's task writes its answer
        # first, and only then is the snapshot's thread woken. Woken with the answer,
        # it would take the interpreter from the loop while the answer is being
        # written (a few tenths of a ms per answer, on a core shared with the loop).
        save, loop = self.snapshot_file.save, asyncio.get_running_loop()
        durable.add_done_callback(lambda _: loop.call_soon(save, snapshot))

    def _answer(
        self, envelope: Envelope, outcome: Outcome, durable: asyncio.Future[None] | None
    ) -> None:
        future = envelope.future
        if future is None or future.done():
            return
        if durable is None:
            future.set_result(outcome)
            return

        def settle(written: asyncio.Future[None]) -> None:
            if future.done():
                return
            if written.cancelled() or written.exception() is not None:
                problem = "cancelled" if written.cancelled() else written.exception()
                log.critical("event %s decided but not journaled: %s", outcome.event_id, problem)
                self._write_failed(str(problem))
                future.set_result(outcome.not_journaled(str(problem)))
            else:
                future.set_result(outcome)

        durable.add_done_callback(settle)

    def _write_failed(self, problem: str) -> None:
        """The record is not on disk: stop the cell, once, and say so."""
        stop_reason = self._ctx.stop_reason
        if stop_reason is not None and stop_reason.code == "JOURNAL_WRITE_FAILED":
            return
        self._post_fault(
            DeviceFault(
                "journal",
                "JOURNAL_WRITE_FAILED",
                f"the journal could not be written ({problem}); records may "
                "be missing: check the disk under the data directory",
            )
        )
