"""The order book: production orders as the cell runs them, kept in the journal.

Why it drives the cell from outside the worker: an order is the operator's
standing command ("make N good parts of this workpiece"), so each part's start
goes through the same door as a person's start (`Cell.command`), decided by
the state machine like any other; the defect limit stops the cell through the
fault path (an ORDER_DEFECT_LIMIT fault: valve closed first, ERROR, the stop
reason saying what to check). Nothing here changes the cell's state itself.

What it decides (docs/operations-guide.md, "Production orders"):

- one order is active (running or held) at a time; others wait queued;
- a trajectory start while an order is active makes a part for it, of its
  workpiece (a start naming another one is refused, 409 naming workpiece_id):
  the cell's decision rules this (`server/core/machine/decide.py`), reading
  `OrderBook.active`;
- a completed run of a running order starts the next part once the cell is
  back in IDLE, the simulated camera presenting a fresh part first;
- a pause leaves the order running (its reason says the cell is paused): the
  cell's Resume continues the part, and the order after it;
- any failed or cancelled run, an e-stop or a fault, the defect limit, and a
  restart of the server hold the order: only POST /orders/{id}/resume
  continues it, and only from IDLE;
- the order completes at its quantity of good parts (then the next queued
  order runs), or an operator closes it (the next queued one is held).
"""

from __future__ import annotations

import asyncio
import json
import logging
import secrets
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from server.core.infra.bus import SubscriptionClosed
from server.core.machine.events import StartPayload
from server.core.machine.transitions import Command, State
from server.core.worker.runs import RunEnded
from server.drivers.base import DeviceFault
from server.orders.model import (
    ACTIVE_STATES,
    GOOD,
    NOT_INSPECTED,
    OPEN_STATES,
    Next,
    Order,
    OrderState,
    Part,
    part_of_run,
)
from server.storage.journal import PART_FIGURES, Journal, Record, records

if TYPE_CHECKING:
    from server.bootstrap.cell import Cell

log = logging.getLogger(__name__)

SOURCE = "order"  # the journal's source of the starts an order makes itself
RESTARTED = "the server restarted while the order was running: resume it once the cell is ready"
# A running order's reason while the cell is paused: it is not held.
PAUSED = "the cell is paused: Resume continues this part and the order"


class OrderRefused(Exception):
    """A request about orders that cannot be done now: nothing was changed.

    `status` is the HTTP answer (404 no such order, 409 not now, 422 a field is wrong).
    """

    def __init__(self, status: int, message: str, field: str | None = None) -> None:
        super().__init__(message)
        self.status = status
        self.message = message
        self.field = field


class OrderBook:
    """Every order the journal keeps, and the one the cell is working through."""

    def __init__(
        self,
        cell: Cell,
        journal: Journal,
        *,
        next_part: Callable[[], None] | None = None,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self._cell = cell
        self._journal = journal
        self._next_part = next_part  # the simulated cell presents a fresh part
        self._clock = clock
        self.orders: dict[str, Order] = {}
        self._tasks: set[asyncio.Task[None]] = set()
        self._watch: asyncio.Task[None] | None = None

    # --- lifecycle -----------------------------------------------------------

    async def start(self) -> None:
        """Load the orders; one that was running is held (never continued by itself)."""
        rows, parts, interrupted = await asyncio.to_thread(self._read)
        for row in rows:
            order = Order(
                order_id=row["order_id"],
                workpiece_id=row["workpiece_id"],
                quantity=int(row["quantity"]),
                defect_limit=int(row["defect_limit"]),
                created_at=float(row["created_at"]),
                created_by=row["created_by"],
                state=OrderState(row["state"]),
                updated_at=float(row["updated_at"]),
                reason=row["reason"],
                idempotency_key=row.get("idempotency_key"),
            )
            self.orders[order.order_id] = order
        for row in parts:
            owner = self.orders.get(row["order_id"])
            if owner is not None:
                owner.parts.append(_part_of_row(row))
        changed: list[Record] = []
        for order in self.orders.values():
            cut_short = self._parts_cut_short(order, interrupted)
            changed.extend(self._part_row(order, part) for part in cut_short)
            if order.state is OrderState.RUNNING or (cut_short and order.state in ACTIVE_STATES):
                # Held, a paused part's order too: its part is counted now, not to come.
                limit = order.defects_in_row >= order.defect_limit
                reason = order.defect_limit_reason() if limit else RESTARTED
                self._set(order, OrderState.HELD, reason)
                changed.append(self._row(order))
                log.warning("order %s held: %s", order.order_id, reason)
        if changed:
            self._journal.append(changed, durable=False)
        self._cell.view.on_run_ended(self._run_ended)
        self._watch = asyncio.create_task(self._watch_states(), name="orders-watch")

    async def stop(self) -> None:
        tasks = [t for t in (self._watch, *self._tasks) if t is not None]
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    def _read(self) -> tuple[list[dict[str, Any]], list[dict[str, Any]], list[dict[str, Any]]]:
        orders = self._journal.query("orders", limit=1_000_000, newest_first=False)
        parts = self._journal.query("order_parts", limit=1_000_000, newest_first=False)
        interrupted = self._journal.query(
            "operations",
            filters={"kind": "trajectory", "outcome": "interrupted"},
            limit=1_000_000,
            newest_first=False,
        )
        return orders, parts, interrupted

    @staticmethod
    def _parts_cut_short(order: Order, runs: list[dict[str, Any]]) -> list[Part]:
        """The order's parts a server stop cut short, added to it, defective: they did not get
        their whole bead. A closed order's too, as a part that ends after the close is.

        The server stopped during the run, so no run end reached the order; the start-up
        closed the run's row as interrupted (server/bootstrap/cell.py: find_interruption).
        """
        counted = {part.run_id for part in order.parts}
        parts = []
        for run in runs:
            params = json.loads(run["params"] or "{}")
            if params.get("order_id") != order.order_id or run["run_id"] in counted:
                continue
            part = part_of_run(
                run["run_id"], "interrupted", run["started_at"], run["ended_at"], None, run["error"]
            )
            order.parts.append(part)
            parts.append(part)
        return parts

    # --- queries -------------------------------------------------------------

    @property
    def active(self) -> Order | None:
        """The order the cell works through (running or held), if any."""
        return next((o for o in self.orders.values() if o.state in ACTIVE_STATES), None)

    def get(self, order_id: str) -> Order:
        order = self.orders.get(order_id)
        if order is None:
            raise OrderRefused(404, f"order {order_id!r} does not exist: GET /orders lists them")
        return order

    def listed(self, state: str | None = None) -> list[Order]:
        """The orders, newest first."""
        found = [o for o in self.orders.values() if state is None or o.state.value == state]
        return sorted(found, key=lambda o: o.created_at, reverse=True)

    # --- commands ------------------------------------------------------------

    def made_with(self, key: str, who: str) -> Order | None:
        """The order `who` made with Idempotency-Key `key`, if any (a retry's answer)."""
        return next(
            (o for o in self.orders.values() if o.idempotency_key == key and o.created_by == who),
            None,
        )

    async def create(
        self,
        workpiece_id: str,
        quantity: int,
        who: str,
        audit: Record | None = None,
        idempotency_key: str | None = None,
    ) -> tuple[Order, str | None]:
        """A new order, running at once if nothing else is active (else queued).

        Returns the order and the run id of its first part (None if queued). With an
        `idempotency_key` the order keeps it, on record, so that a retry (`made_with`)
        finds it after a restart too.
        """
        library = self._cell.stores.workpieces if self._cell.stores else None
        if library is None or not await asyncio.to_thread(library.exists, workpiece_id):
            raise OrderRefused(  # a valid id the library lacks: 409, as for POST /start
                409,
                f"workpiece {workpiece_id!r} is not in the library: GET /workpieces lists them",
                "workpiece_id",
            )
        queued = self.active is not None
        if not queued:
            self._refuse_unless_startable()
        now = self._clock()
        order = Order(
            order_id=f"ord-{secrets.token_hex(4)}",
            workpiece_id=workpiece_id,
            quantity=quantity,
            defect_limit=self._cell.settings.order_defect_limit,
            created_at=now,
            created_by=who,
            state=OrderState.QUEUED if queued else OrderState.RUNNING,
            updated_at=now,
            idempotency_key=idempotency_key,
        )
        await self._write([self._row(order), *([audit] if audit else [])])
        self.orders[order.order_id] = order  # once on record
        if queued:
            return order, None
        return order, await self._start_part(order)

    async def close(self, order_id: str, who: str, audit: Record | None = None) -> Order:
        """End an order before its quantity; a run under way is not stopped (cancel does)."""
        order = self.get(order_id)
        if order.state not in OPEN_STATES:
            raise OrderRefused(409, f"order {order_id} is {order.state.value}: nothing to close")
        was_active = order.state in ACTIVE_STATES
        follower = self._next_queued() if was_active else None
        undo = [order, *([follower] if follower else [])]
        saved = [(o, o.state, o.reason, o.updated_at) for o in undo]
        self._set(order, OrderState.CLOSED, f"closed by {who}")
        rows = [self._row(order)]
        if follower is not None:
            reason = f"the order before it ({order_id}) was closed: resume it to start"
            self._set(follower, OrderState.HELD, reason)
            rows.append(self._row(follower))
        try:
            await self._write([*rows, *([audit] if audit else [])])
        except BaseException:
            for o, state, reason_before, updated_at in saved:
                o.state, o.reason, o.updated_at = state, reason_before, updated_at
            raise
        return order

    async def resume(self, order_id: str, audit: Record | None = None) -> tuple[Order, str | None]:
        """Continue a held order from IDLE: a fresh part is presented and started."""
        order = self.get(order_id)
        if order.state is not OrderState.HELD:
            raise OrderRefused(
                409, f"order {order_id} is {order.state.value}: only a held order resumes"
            )
        self._refuse_unless_startable()
        saved = (order.state, order.reason, order.updated_at)
        self._set(order, OrderState.RUNNING, None)
        try:
            await self._write([self._row(order), *([audit] if audit else [])])
        except BaseException:
            order.state, order.reason, order.updated_at = saved
            raise
        self._present_next_part()
        return order, await self._start_part(order)

    # --- the cell's side -----------------------------------------------------

    def _refuse_unless_startable(self) -> None:
        allowed, reason = self._cell.view.allowed(Command.START)
        if not allowed:
            raise OrderRefused(409, f"the cell cannot start a part now: {reason}")

    async def _start_part(self, order: Order) -> str | None:
        """Start the order's next part; a refused start holds the order with its reason."""
        payload = StartPayload(True, order.workpiece_id, order.order_id)
        try:
            outcome = await self._cell.command(Command.START, source=SOURCE, payload=payload)
        except Exception as exc:  # queue full, journal down, shutting down: hold, say why
            problem = str(exc) or type(exc).__name__
        else:
            if outcome.accepted:
                return outcome.run_id
            problem = outcome.message
        if order.state is OrderState.RUNNING:
            self._set(order, OrderState.HELD, f"the next part could not start: {problem}")
            self._journal.append([self._row(order)], durable=False)
            log.warning("order %s held: %s", order.order_id, order.reason)
        return None

    def _present_next_part(self) -> None:
        if self._next_part is not None:
            self._next_part()

    def _run_ended(self, ended: RunEnded) -> None:
        """A run ended (in the worker, before its state changes: never block here)."""
        if ended.operation != "trajectory":
            return
        order = self.orders.get(str(ended.params.get("order_id") or ""))
        if order is None:
            return
        now = self._clock()
        part = part_of_run(
            ended.run_id, ended.outcome, now - ended.seconds, now, ended.result, ended.error
        )
        if order.state not in ACTIVE_STATES:  # closed meanwhile: the part is still reported
            order.parts.append(part)
            self._journal.append([self._part_row(order, part)], durable=False)
            return
        following = order.count(part)
        rows = [self._part_row(order, part)]
        start_next: Order | None = None
        if following is Next.COMPLETE:
            self._set(order, OrderState.COMPLETED, order.completed_reason())
            follower = self._next_queued()
            if follower is not None:
                self._set(follower, OrderState.RUNNING, None)
                rows.append(self._row(follower))
                start_next = follower
        elif following is Next.DEFECT_LIMIT:
            self._set(order, OrderState.HELD, order.defect_limit_reason())
            fault = DeviceFault("quality", "ORDER_DEFECT_LIMIT", order.reason or "")
            self._cell.report_fault(fault)
        elif part.outcome != "completed":
            self._set(order, OrderState.HELD, f"part {len(order.parts)}: {part.reasons[0]}")
        elif order.state is OrderState.RUNNING:
            start_next = order
        rows.insert(0, self._row(order))
        self._journal.append(rows, durable=False)
        if order.state is OrderState.HELD:
            log.warning("order %s held: %s", order.order_id, order.reason)
        if start_next is not None:
            self._spawn(self._continue(start_next))

    async def _continue(self, order: Order) -> None:
        """The next part, decided after the run's end (the worker is back in IDLE by then)."""
        if order.state is not OrderState.RUNNING:
            return
        self._present_next_part()
        await self._start_part(order)

    async def _watch_states(self) -> None:
        """Hold the running order when the cell pauses or stops (ERROR)."""
        while True:
            subscription = self._cell.bus.subscribe(types=["state_changed"])
            try:
                while True:
                    message = await subscription.get()
                    self._hold_on(str(message.data.get("new_state")), message.data)
            except SubscriptionClosed:
                continue
            finally:
                self._cell.bus.unsubscribe(subscription)

    def _hold_on(self, state: str, data: dict[str, Any]) -> None:
        order = self.active
        if order is None or order.state is not OrderState.RUNNING:
            return
        if state == State.PAUSED.value:
            # Not held: Resume continues the part, and the order after it.
            self._note(order, PAUSED)
            return
        if state == State.EXECUTING_TRAJECTORY.value:
            if order.reason == PAUSED:  # resumed: the part goes on, and the order
                self._note(order, None)
            return
        if state == State.ERROR.value:
            stop = ((data.get("snapshot") or {}).get("stop_reason") or {}).get("message")
            reason = f"the cell stopped ({stop or data.get('event')}): reset, then resume"
        else:
            return
        self._set(order, OrderState.HELD, reason)
        self._journal.append([self._row(order)], durable=False)
        log.warning("order %s held: %s", order.order_id, reason)

    # --- bookkeeping ---------------------------------------------------------

    def _note(self, order: Order, reason: str | None) -> None:
        """A running order's reason changed (the cell paused, or resumed), on record."""
        self._set(order, OrderState.RUNNING, reason)
        self._journal.append([self._row(order)], durable=False)

    def _next_queued(self) -> Order | None:
        queued = [o for o in self.orders.values() if o.state is OrderState.QUEUED]
        return min(queued, key=lambda o: o.created_at) if queued else None

    def _set(self, order: Order, state: OrderState, reason: str | None) -> None:
        order.state = state
        order.reason = reason
        order.updated_at = self._clock()

    def _spawn(self, work: Any) -> None:
        task = asyncio.get_running_loop().create_task(work)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _write(self, rows: list[Record]) -> None:
        """Commit `rows` and wait for it (the caller puts memory back if it fails)."""
        written = self._journal.append(rows)
        if written is not None:
            await written

    @staticmethod
    def _row(order: Order) -> Record:
        return records.order(
            order_id=order.order_id,
            created_at=order.created_at,
            workpiece_id=order.workpiece_id,
            quantity=order.quantity,
            defect_limit=order.defect_limit,
            state=order.state.value,
            reason=order.reason,
            created_by=order.created_by,
            updated_at=order.updated_at,
            idempotency_key=order.idempotency_key,
        )

    @staticmethod
    def _part_row(order: Order, part: Part) -> Record:
        return records.order_part(
            time=part.ended_at,
            order_id=order.order_id,
            run_id=part.run_id,
            started_at=part.started_at,
            outcome=part.outcome,
            verdict=part.verdict,
            inspected=part.inspected,
            reasons=list(part.reasons),
            **part.measured,
        )


def _part_of_row(row: dict[str, Any]) -> Part:
    inspected = bool(row["inspected"])
    verdict = row["verdict"]
    if verdict == GOOD and not inspected:  # recorded before parts nobody judged had their word
        verdict = NOT_INSPECTED
    return Part(
        run_id=row["run_id"],
        started_at=row["started_at"],
        ended_at=float(row["time"]),
        outcome=row["outcome"],
        verdict=verdict,
        inspected=inspected,
        reasons=tuple(json.loads(row["reasons"] or "[]")),
        figures={name: row[name] for name in PART_FIGURES},
    )
