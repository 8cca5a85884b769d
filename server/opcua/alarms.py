"""The cell's faults and warnings as OPC UA alarms: events of alarm condition types.

A fault stopped the cell: a TripAlarmType event (an OffNormalAlarmType whose equipment
has tripped). A warning did not: an OffNormalAlarmType event. What each is, when it
clears and how acknowledging works is `server/opcua/conditions.py`; this module puts it
on the wire. Each event is emitted on the cell's object and on the Server object (both
with EventNotifier SubscribeToEvents, the cell a notifier of the Server), so a client
subscribed to either sees it: `uasubscribe -t event` subscribes to the Server.

Every condition has a node, `<cell_id>.Alarms.<CODE>` in the cell's namespace (its
ConditionId, typed TripAlarmType or OffNormalAlarmType), made the first time its code
is raised, with the type's variables (ActiveState/Id, AckedState/Id, Retain, Severity,
Message...) kept as its latest event says (server/opcua/condition_nodes.py). A client
acknowledges or confirms it with the standard methods, AcknowledgeableConditionType's
Acknowledge (i=9111) and Confirm (i=9113), called on the ConditionId with the notice's
EventId and a comment. Who may: Acknowledge the operator role and above (whoever runs
the cell has seen the alarm), Confirm the maintenance role and above (the cause is dealt
with, the role that resets the cell); anonymous never. Each call is audited in the
journal like the cell's commands, accepted or refused, with the session's principal; an
accepted one is on disk before the condition changes and the answer goes.
ConditionRefresh (i=3875) sends the retained conditions between a RefreshStartEvent and
a RefreshEndEvent, as alarm clients ask after (re)connecting.

The follower is a bus subscriber of its own (bounded buffer, never waited on), taking
`error`, `alert`, `alert_cleared` (a warning's cause gone) and `state_changed`, each
once the commands being answered have gone (server/core/infra/answers_in_flight.py), as
the tags do.
"""

from __future__ import annotations

import asyncio
import contextlib
import copy
import logging
import sqlite3
import time
from datetime import UTC, datetime
from typing import Any, Final

from asyncua import Node, Server, ua
from asyncua.common import event_objects

from server.bootstrap.cell import Cell
from server.core.infra.answers_in_flight import AnswersInFlight, after_answers
from server.core.infra.bus import BusMessage, Subscription, SubscriptionClosed
from server.opcua.address_space import node_id_of
from server.opcua.condition_nodes import ConditionNodes
from server.opcua.conditions import Condition, ConditionBook, ConditionClass, Notice, Refused
from server.opcua.identity import ANONYMOUS, caller
from server.opcua.methods import peer_of
from server.security.tokens import Role, TokenStore
from server.storage.journal import records

log = logging.getLogger(__name__)


def _node(number: int) -> ua.NodeId:
    """A node id of OPC UA's own namespace."""
    return ua.NodeId(ua.Int32(number))


BUS_BUFFER = 1024
FOLLOWED: Final = ("error", "alert", "alert_cleared", "state_changed")
ACKNOWLEDGE: Final = _node(ua.ObjectIds.AcknowledgeableConditionType_Acknowledge)
CONFIRM: Final = _node(ua.ObjectIds.AcknowledgeableConditionType_Confirm)
REFRESH: Final = _node(ua.ObjectIds.ConditionType_ConditionRefresh)
SERVER: Final = _node(ua.ObjectIds.Server)
# The least role each method needs (see the module docstring).
ROLES: Final = {"Acknowledge": Role.OPERATOR, "Confirm": Role.MAINTENANCE}
TYPES: Final = {"fault": ua.ObjectIds.TripAlarmType, "warning": ua.ObjectIds.OffNormalAlarmType}
CLASSES: Final = {
    ConditionClass.SAFETY: (ua.ObjectIds.SafetyConditionClassType, "Safety"),
    ConditionClass.PROCESS: (ua.ObjectIds.ProcessConditionClassType, "Process"),
    ConditionClass.MAINTENANCE: (ua.ObjectIds.MaintenanceConditionClassType, "Maintenance"),
}
# The fields set on each notice, with their types (asyncua's templates type a few of
# them by data type node, which a Variant cannot take).
FIELD_TYPES: Final = {
    "NodeId": ua.VariantType.NodeId,
    "ActiveState/TransitionTime": ua.VariantType.DateTime,
    "AckedState/TransitionTime": ua.VariantType.DateTime,
    "ConfirmedState/TransitionTime": ua.VariantType.DateTime,
    "EnabledState/TransitionTime": ua.VariantType.DateTime,
}


def _status(code: int) -> ua.StatusCode:
    return ua.StatusCode(ua.UInt32(code))


def _stamp(at: float) -> datetime:
    return datetime.fromtimestamp(at, UTC)


def _two_state(event: Any, name: str, value: bool, true: str, false: str, at: float) -> None:
    setattr(event, name, ua.LocalizedText(true if value else false))
    setattr(event, f"{name}/Id", value)
    if f"{name}/TransitionTime" in event.data_types:
        setattr(event, f"{name}/TransitionTime", _stamp(at))


NULL: Final = ua.Variant(None)  # a field the event does not have


def _fields_shared(template: Any) -> Any:
    """`template` with its class swapped for one whose notifications share the event's
    values instead of deep-copying each one (`to_event_fields`).

    Why: asyncua deep-copies every selected field for every subscriber, because a
    generator's one event object is changed in place for its next trigger. Each
    notice here is a fresh copy of the template whose fields are set to new values
    and never changed after it is triggered, so sharing them is safe, and a field
    still holding the template's value keeps its Variant from one notice to the next
    (most of the eighty-odd fields a client selects). Those copies would be most of
    the work a notice puts on the event loop just after its transition
    (bench.plant_latency).
    """
    base = type(template)
    kept: dict[str, tuple[object, ua.Variant]] = {}  # field -> (the value, its Variant)

    def variant(self: Any, name: str) -> ua.Variant:
        value = getattr(self, name, None)
        if value is None:
            return NULL
        known = kept.get(name)
        if known is not None and known[0] is value:
            return known[1]
        made = ua.Variant(value, self.data_types[name])
        if getattr(template, name, None) is value:
            kept[name] = (value, made)
        return made

    def to_event_fields(self: Any, clauses: list[ua.SimpleAttributeOperand]) -> list[ua.Variant]:
        return [
            variant(
                self,
                self.browse_path_to_attribute_name(operand.BrowsePath)
                if operand.BrowsePath
                else ua.AttributeIds(operand.AttributeId).name,
            )
            for operand in clauses
        ]

    template.__class__ = type(base.__name__, (base,), {"to_event_fields": to_event_fields})
    return template


def _text(value: object) -> str:
    value = value.Value if isinstance(value, ua.Variant) else value
    if isinstance(value, ua.LocalizedText):
        return value.Text or ""
    return "" if value is None else str(value)


class CellAlarms:
    """The alarm conditions of one cell's OPC UA object."""

    def __init__(
        self,
        server: Server,
        cell: Cell,
        tokens: TokenStore,
        answers: AnswersInFlight | None = None,
    ) -> None:
        self.server = server
        self.cell = cell
        self.tokens = tokens
        self.answers = answers
        self.book = ConditionBook()
        self._templates: dict[str, Any] = {}
        self._codes: dict[ua.NodeId, str] = {}
        self._nodes: dict[str, ua.NodeId] = {}
        self._lock = asyncio.Lock()  # one Acknowledge or Confirm at a time
        self._subscription: Subscription | None = None
        self._task: asyncio.Task[None] | None = None
        self._cell_node: ua.NodeId | None = None
        self._cell_id = ""
        self._namespace = 0
        self._folder: ua.NodeId | None = None
        self.condition_nodes = ConditionNodes(
            server, {"Acknowledge": self._acknowledge, "Confirm": self._confirm}
        )

    async def install(self, cell: Node, cell_id: str, namespace: int) -> None:
        """The cell and the Server as event notifiers, the Alarms folder, the methods."""
        server = self.server
        self._cell_node, self._cell_id, self._namespace = cell.nodeid, cell_id, namespace
        for kind, type_id in TYPES.items():
            generator = await server.get_event_generator(type_id, cell.nodeid)
            template = _fields_shared(generator.event)
            template.data_types = {**template.data_types, **FIELD_TYPES}
            template.NodeId = None
            self._templates[kind] = template
        await server.get_node(SERVER).set_event_notifier([ua.EventNotifier.SubscribeToEvents])
        await server.get_node(SERVER).add_reference(
            cell.nodeid, ua.ObjectIds.HasNotifier, forward=True, bidirectional=False
        )
        folder = await cell.add_folder(
            node_id_of(namespace, f"{cell_id}.Alarms"), ua.QualifiedName("Alarms", namespace)
        )
        self._folder = folder.nodeid
        server.link_method(server.get_node(ACKNOWLEDGE), self._acknowledge)
        server.link_method(server.get_node(CONFIRM), self._confirm)
        server.link_method(server.get_node(REFRESH), self._refresh)

    def subscribe(self) -> None:
        """Follow the bus from now on (before the server starts: nothing falls between)."""
        self._subscription = self.cell.bus.subscribe(BUS_BUFFER, FOLLOWED)

    async def start(self) -> None:
        """Raise what the cell holds now (a fault it started in, a damaged journal, the
        standing warnings), then follow the bus."""
        snapshot = self.cell.view.snapshot()
        reason = snapshot.get("stop_reason")
        now = time.time()
        if reason:
            data = {**reason, "state": snapshot.get("state")}
            for notice in self.book.on_message("error", data, self.cell.bus.last_seq, now):
                await self._emit(notice)
        journal = self.cell.journal
        for damage in journal.damage if journal is not None else ():
            data = {
                "code": "JOURNAL_DAMAGED",
                "message": damage.message,
                "component": "journal",
                "classification": "warning",
                "state": "",
                "time": damage.found_at,
            }
            for notice in self.book.on_message("alert", data, self.cell.bus.last_seq, now):
                await self._emit(notice)
        # The standing warnings raised before this follower subscribed (the cell starts
        # first: its first care check may have found an item due by now).
        worker = self.cell.worker
        for data in list(worker.alerts.standing.values()) if worker is not None else ():
            if data["code"] not in self.book.conditions:
                for notice in self.book.on_message("alert", data, self.cell.bus.last_seq, now):
                    await self._emit(notice)
        self._task = asyncio.create_task(self._follow(), name="opcua-alarms")

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        if self._subscription is not None:
            self._subscription.close()

    # --- following the bus --------------------------------------------------------------

    async def _follow(self) -> None:
        assert self._subscription is not None
        while True:
            try:
                message = await self._subscription.get()
            except SubscriptionClosed as closed:
                log.warning("OPC UA alarms fell behind the bus (%s); catching up", closed.reason)
                self._subscription = self.cell.bus.subscribe(BUS_BUFFER, FOLLOWED)
                if not self.cell.view.snapshot().get("stop_reason"):
                    for notice in self.book.clear_all_faults(time.time()):
                        await self._emit(notice)
                continue
            if message.type == "state_changed" and self.cell.journal is not None:
                await self.cell.journal.caught_up()  # the transition's commit first
            await after_answers(self.answers)  # and the command's answer
            try:
                await self._apply(message)
            except Exception:  # an event not emitted must not end the follower
                log.exception("OPC UA: could not emit the alarms of bus message %d", message.seq)

    async def _apply(self, message: BusMessage) -> None:
        for notice in self.book.on_message(message.type, message.data, message.seq, message.time):
            await self._emit(notice)

    # --- emitting -------------------------------------------------------------------------

    async def _condition_node(self, condition: Condition) -> ua.NodeId:
        """The condition's node (its ConditionId), made the first time its code is raised."""
        known = self._nodes.get(condition.code)
        if known is not None:
            return known
        assert self._folder is not None and self._cell_node is not None
        node_id = node_id_of(self._namespace, f"{self._cell_id}.Alarms.{condition.code}")
        await self.condition_nodes.make(
            condition.code,
            node_id,
            TYPES[condition.kind],
            self._folder,
            self._cell_node,
            f"the cell's {condition.kind} {condition.code}",
        )
        self._nodes[condition.code] = node_id
        self._codes[node_id] = condition.code
        return node_id

    async def _emit(self, notice: Notice, subscription_id: int | None = None) -> None:
        """The condition as it is now, on the cell and on the Server."""
        condition = notice.condition
        event = await self._event(condition)
        # The node's variables first: a client reading them after the event sees the same.
        await self.condition_nodes.write(condition.code, event, condition.changed_at)
        service = self.server.iserver.isession.subscription_service
        assert self._cell_node is not None
        for emitter in (self._cell_node, SERVER):
            copied = copy.copy(event)
            copied.emitting_node = emitter
            await service.trigger_event(copied, subscription_id=subscription_id)
        log.debug("OPC UA alarm %s %s", condition.code, notice.why)

    async def _event(self, condition: Condition) -> Any:
        template = self._templates[condition.kind]
        event = copy.copy(template)
        class_id, class_name = CLASSES[condition.condition_class]
        now = datetime.now(UTC)
        event.EventId = condition.event_id
        event.NodeId = await self._condition_node(condition)
        event.SourceName = condition.component or self._cell_id
        event.Time = _stamp(condition.changed_at)
        event.ReceiveTime = now
        event.Message = ua.LocalizedText(condition.message)
        event.Severity = condition.severity
        event.LastSeverity = condition.severity
        event.ConditionClassId = _node(class_id)
        event.ConditionClassName = ua.LocalizedText(class_name)
        event.ConditionName = condition.code
        event.BranchId = ua.NodeId()
        event.Retain = condition.retain
        event.Quality = _status(ua.StatusCodes.Good)
        event.Comment = ua.LocalizedText(condition.comment)
        event.ClientUserId = condition.user
        event.FirstInGroupFlag = condition.first_out
        event.SuppressedOrShelved = False
        _two_state(event, "EnabledState", True, "Enabled", "Disabled", condition.raised_at)
        active_since = condition.raised_at if condition.active else condition.changed_at
        _two_state(event, "ActiveState", condition.active, "Active", "Inactive", active_since)
        at = condition.changed_at
        _two_state(event, "AckedState", condition.acked, "Acknowledged", "Unacknowledged", at)
        _two_state(event, "ConfirmedState", condition.confirmed, "Confirmed", "Unconfirmed", at)
        return event

    # --- what clients call -----------------------------------------------------------------

    async def _acknowledge(self, parent: ua.NodeId, *args: Any) -> ua.StatusCode:
        return await self._respond("Acknowledge", parent, args)

    async def _confirm(self, parent: ua.NodeId, *args: Any) -> ua.StatusCode:
        return await self._respond("Confirm", parent, args)

    async def _respond(self, name: str, parent: ua.NodeId, args: tuple[Any, ...]) -> ua.StatusCode:
        """Check who calls and what, audit it, then change the condition and emit it."""
        user = caller.get()
        address = peer_of(self.server, user)
        action = f"OPC UA {name}"
        principal = user.principal(self.tokens) if user is not None else None
        code = self._codes.get(parent)
        what = code or parent.to_string()
        if principal is None:
            why = "authentication required: sign in with an API token as the password"
            return self._refused(ANONYMOUS, address, action, what, why, "BadUserAccessDenied")
        who = principal.describe()
        needed = ROLES[name]
        if principal.role < needed:
            why = f"this needs the {needed.label} role; {principal.name} has {principal.role.label}"
            return self._refused(who, address, action, what, why, "BadUserAccessDenied")
        values = [a.Value if isinstance(a, ua.Variant) else a for a in args]
        if len(values) != 2 or not isinstance(values[0], bytes):
            why = f"{name} takes the notice's EventId (ByteString) and a comment"
            return self._refused(who, address, action, what, why, "BadInvalidArgument")
        event_id, comment = values[0], _text(values[1])
        if code is None:
            why = "not a condition of this cell"
            return self._refused(who, address, action, what, why, "BadNodeIdUnknown")
        async with self._lock:
            change = self.book.acknowledge if name == "Acknowledge" else self.book.confirm
            check = self.book.check(name, code, event_id)
            if check is not None:
                return self._refused(who, address, action, what, _WHY[check], check.value)
            detail = f"{code}: {comment}" if comment else code
            row = records.audit(time.time(), who, address, action, "accepted", detail)
            written = self.cell.journal.append([row]) if self.cell.journal is not None else None
            if written is not None:
                try:
                    await written
                except (sqlite3.Error, OSError) as exc:
                    log.error(
                        "%s from %s not done: the journal cannot write (%s)", action, address, exc
                    )
                    return _status(ua.StatusCodes.BadResourceUnavailable)
            notice = change(code, event_id, comment, principal.name, time.time())
            assert not isinstance(notice, Refused)  # checked under the same lock
        await self._emit(notice)
        log.info("%s of %s by %s from %s", action, code, principal.name, address)
        return _status(ua.StatusCodes.Good)

    def _refused(
        self, who: str, address: str, action: str, what: str, why: str, status: str
    ) -> ua.StatusCode:
        journal = self.cell.journal
        if journal is not None:
            row = records.audit(
                time.time(), who, address, action, f"refused ({status})", f"{what}: {why}"
            )
            journal.append([row], durable=False)
        log.info("%s of %s from %s refused: %s", action, what, address, why)
        return _status(getattr(ua.StatusCodes, status))

    async def _refresh(self, parent: ua.NodeId, *args: Any) -> ua.StatusCode:
        """ConditionRefresh(SubscriptionId): the retained conditions to that subscription,
        between a RefreshStartEvent and a RefreshEndEvent."""
        values = [a.Value if isinstance(a, ua.Variant) else a for a in args]
        if not values or not isinstance(values[0], int):
            return _status(ua.StatusCodes.BadInvalidArgument)
        subscription_id = values[0]
        if subscription_id not in self.server.iserver.isession.subscription_service.subscriptions:
            return _status(ua.StatusCodes.BadSubscriptionIdInvalid)
        await self._refresh_marker(event_objects.RefreshStartEvent(), subscription_id)
        for condition in self.book.retained():
            await self._emit(Notice(condition, "refreshed"), subscription_id)
        await self._refresh_marker(event_objects.RefreshEndEvent(), subscription_id)
        return _status(ua.StatusCodes.Good)

    async def _refresh_marker(self, marker: Any, subscription_id: int) -> None:
        """A RefreshStartEvent or RefreshEndEvent from the Server, to one subscription."""
        service = self.server.iserver.isession.subscription_service
        assert self._cell_node is not None
        marker.SourceNode = SERVER
        marker.SourceName = "Server"
        marker.EventId = f"refresh-{time.time_ns()}".encode()
        marker.Time = marker.ReceiveTime = datetime.now(UTC)
        for emitter in (self._cell_node, SERVER):
            event = copy.copy(marker)
            event.emitting_node = emitter
            await service.trigger_event(event, subscription_id=subscription_id)


_WHY: Final = {
    Refused.UNKNOWN_CONDITION: "not a condition of this cell",
    Refused.EVENT_ID_UNKNOWN: "the EventId is not the condition's latest notice: refresh and retry",
    Refused.ALREADY_ACKED: "the condition is already acknowledged",
    Refused.ALREADY_CONFIRMED: "the condition is already confirmed (or not acknowledged yet)",
}
