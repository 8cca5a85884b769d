"""The cell's OPC UA methods: the operator's commands on the HTTP command path and roles.

Each method is a command of the catalogue (server/commands/catalogue.py) that
names an OPC UA method, sent through `Cell.command` with an audit note naming
the token's principal, the client's address and the method, exactly as
server/api/commands.py sends the HTTP command; the role it needs is the
catalogue's, which the HTTP gate reads too, so the doors cannot drift apart. EmergencyStop is
the e-stop of POST /estop (`Cell.command(Command.ESTOP)`: the devices halted
first, then the event ahead of everything queued) and, like it, open to every
signed-in role.

The answer: Good with (Accepted, State, Message, EventId) as output arguments;
a refusal is a Bad status (BadUserAccessDenied for a missing token or role,
BadInvalidState where HTTP says 409, BadInvalidArgument for 422,
BadResourceUnavailable for 503) with the same output arguments, so the cell's
message comes back with it.

The inputs are checked by the command's own request model and turned into the
worker's payload by the same function (server/commands/answers.py: `payload_of`,
which HTTP and MQTT use too): a part id HTTP refuses with 422 is refused here with
BadInvalidArgument, the 422's detail as the message and the audit row's detail.
A Call request too large to be a method's (server/opcua/protection.py) never
reaches a method: BadRequestTooLarge, as HTTP answers 413.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any, Final

from asyncua import Server, ua
from asyncua.common.callback import ServerItemCallback

from server.bootstrap.cell import Cell
from server.commands.answers import Problem, invalid_request, payload_of
from server.commands.answers import status_of as http_status_of
from server.commands.catalogue import CATALOGUE, is_stop
from server.common.errors import EventQueueFull, JournalUnavailable, WorkerStopped
from server.core.machine.events import AuditNote, Outcome
from server.core.machine.transitions import Command
from server.opcua.address_space import node_id_of
from server.opcua.call_lane import ASKED_AT_ESTOPS
from server.opcua.identity import ANONYMOUS, CellUser, caller
from server.opcua.nodes import add_method
from server.security.tokens import Role, TokenStore
from server.storage.journal import records

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Method:
    """One OPC UA method: its PackML name (None: the cell's own, as Purge), the command it
    sends and the role it needs."""

    name: str
    packml: str | None
    command: Command | None  # None: a PackML method the OPC UA layer carries out itself
    role: Role
    description: str


# One method per catalogue entry that names one, in the catalogue's order.
METHODS: Final = tuple(
    Method(spec.opcua.name, spec.opcua.packml, spec.command, spec.role, spec.opcua.description)
    for spec in CATALOGUE
    if spec.opcua is not None
)
OUTPUTS: Final = (
    ("Accepted", ua.VariantType.Boolean),
    ("State", ua.VariantType.String),
    ("Message", ua.VariantType.String),
    ("EventId", ua.VariantType.String),
)
INPUTS: Final = {"Start": (("WorkpieceId", ua.VariantType.String),)}
Gate = Callable[[], str | None]  # a reason the PackML state refuses a call now, or None


@dataclass(frozen=True)
class Admitted:
    """A call that passed the checks: who made it, from where, and the worker's payload."""

    who: str
    address: str
    action: str
    payload: Any


# The OPC UA status for each HTTP status a command's answer can have.
_CODES: Final = {
    202: ua.StatusCodes.Good,
    409: ua.StatusCodes.BadInvalidState,
    422: ua.StatusCodes.BadInvalidArgument,
    503: ua.StatusCodes.BadResourceUnavailable,
}


def status_of(outcome: Outcome) -> int:
    """The status code of the worker's answer: HTTP's (`answers.status_of`) in OPC UA's terms."""
    return int(_CODES[http_status_of(outcome)])


def status_name(code: int) -> str:
    return ua.StatusCode(ua.UInt32(code)).name


def answer(
    code: int, accepted: bool, state: str, message: str, event_id: str
) -> ua.CallMethodResult:
    result = ua.CallMethodResult()
    result.StatusCode = ua.StatusCode(ua.UInt32(code))
    values = (accepted, state, message, event_id)
    result.OutputArguments = [
        ua.Variant(value, kind) for value, (_, kind) in zip(values, OUTPUTS, strict=True)
    ]
    return result


def _label(outcome: Outcome) -> str:
    code = status_of(outcome)
    return "accepted" if code == ua.StatusCodes.Good else f"refused ({status_name(code)})"


def peer_of(server: Server, user: CellUser | None) -> str:
    """The address of the session `user` signed in on ("unknown" if not found).

    asyncua names each external session after its peer (host, port); it keeps them
    in a private map, read here only to name the caller in the audit trail.
    """
    sessions = getattr(server.iserver, "_external_sessions", {})
    for session in list(sessions.values()):
        if user is not None and session.user is user:
            name = session.name
            return str(name[0]) if isinstance(name, tuple) and name else str(name)
    return "unknown"


def body_of(method: Method, args: tuple[Any, ...]) -> tuple[Any, list[Problem]]:
    """The HTTP request body a method's input arguments stand for, for the route's model.

    Start's WorkpieceId is `{"contour_matching": false, "workpiece_id": ...}` (empty or
    null: `{}`, find the part on the table), its value passed as the client sent it: a
    number or an array where the string belongs is refused by the model, naming
    `workpiece_id`, as HTTP refuses it. More arguments than the method declares are a
    problem too (HTTP refuses a field it does not know). The other methods take none.
    """
    declared = INPUTS.get(method.name, ())
    values = [arg.Value if isinstance(arg, ua.Variant) else arg for arg in args]
    if declared and len(values) > len(declared):
        names = ", ".join(name for name, _ in declared)
        message = (
            f"{method.name} takes {len(declared)} input argument(s) ({names}), got {len(values)}"
        )
        return None, [{"field": "arguments", "message": message, "type": "too_many_arguments"}]
    if method.command is Command.START:
        workpiece = values[0] if values else None
        if workpiece is None or workpiece == "":
            return {}, []
        return {"contour_matching": False, "workpiece_id": workpiece}, []
    return None, []


class CellMethods:
    """The method callbacks of one cell object."""

    def __init__(self, server: Server, cell: Cell, tokens: TokenStore) -> None:
        self.server = server
        self.cell = cell
        self.tokens = tokens
        self.nodes: dict[ua.NodeId, Method] = {}

    async def add(self, parent: ua.NodeId, cell_id: str, namespace: int) -> None:
        """The cell's own methods under its object; every id a string (the arguments'
        too: `<cell_id>.<Method>.InputArguments`), the same at every start."""
        for method in METHODS:
            inputs = [self._argument(name, kind) for name, kind in INPUTS.get(method.name, ())]
            outputs = [self._argument(name, kind) for name, kind in OUTPUTS]
            node_id = node_id_of(namespace, f"{cell_id}.{method.name}")
            self.nodes[node_id] = method
            await add_method(
                self.server,
                parent,
                node_id,
                ua.QualifiedName(method.name, namespace),
                inputs,
                outputs,
                callback=self._callback(method),
                description=(
                    f"PackML {method.packml}: {method.description}"
                    if method.packml is not None
                    else method.description
                ),
            )

    def is_stop(self, node_id: ua.NodeId) -> bool:
        """Whether the method at `node_id` is a stop (EmergencyStop, PackML's Abort)."""
        method = self.nodes.get(node_id)
        return method is not None and is_stop(method.command)

    def may_call(self, user: object, method: Method) -> bool:
        """Whether `user` holds a token with the role `method` needs (anonymous: never)."""
        principal = user.principal(self.tokens) if isinstance(user, CellUser) else None
        return principal is not None and principal.role >= method.role

    def user_executable(self, event: ServerItemCallback, dispatcher: object) -> None:
        """asyncua's PostRead callback: a method's UserExecutable as this session may call it.

        asyncua keeps one UserExecutable per node (true); a client reads it to grey out a
        method it may not call, so each session is told its own: false for anonymous and
        for a role too low, as the call itself would be refused. The stored value is left
        alone: the answer's entry is replaced, not changed.
        """
        results = event.response_params
        for index, item in enumerate(event.request_params.NodesToRead):
            method = self.nodes.get(item.NodeId)
            if (
                method is None
                or item.AttributeId != ua.AttributeIds.UserExecutable
                or index >= len(results)
                or not results[index].StatusCode.is_good()
            ):
                continue
            allowed = self.may_call(event.user, method)
            results[index] = ua.DataValue(ua.Variant(allowed, ua.VariantType.Boolean))

    @staticmethod
    def _argument(name: str, kind: ua.VariantType) -> ua.Argument:
        argument = ua.Argument()
        argument.Name = name
        argument.DataType = ua.NodeId(ua.Int32(kind.value))
        argument.ValueRank = -1
        return argument

    def _callback(self, method: Method) -> Callable[..., Awaitable[ua.CallMethodResult]]:
        async def call(parent: ua.NodeId, *args: Any) -> ua.CallMethodResult:
            return await self.call(method, args)

        return call

    def admit(
        self, method: Method, args: tuple[Any, ...], gate: Gate | None = None
    ) -> Admitted | ua.CallMethodResult:
        """Who calls, with which role and inputs, and whether the PackML state takes the
        call now (`gate`: a reason to refuse, or None): admitted, or the refusal."""
        user = caller.get()
        address = peer_of(self.server, user)
        action = f"OPC UA {method.name}"
        principal = user.principal(self.tokens) if user is not None else None
        needed = method.role
        if principal is None:
            why = (
                "authentication required: sign in with an API token as the password"
                if user is None or user.token is None
                else "the token is unknown or revoked"
            )
            return self._refuse(ANONYMOUS, address, action, why)
        if principal.role < needed:
            why = f"this needs the {needed.label} role; {principal.name} has {principal.role.label}"
            return self._refuse(principal.describe(), address, action, why)
        # The route's own model checks the inputs, as over HTTP and MQTT: the same
        # refusal (the 422's detail as the message), audited alike, nothing sent.
        body, problems = body_of(method, args)
        payload = None
        if not problems and method.command is not None:
            payload, problems = payload_of(method.command, body)
        if problems:
            why = invalid_request(problems)
            return self._refuse(
                principal.describe(), address, action, why, ua.StatusCodes.BadInvalidArgument
            )
        why_not = gate() if gate is not None else None
        if why_not is not None:
            return self._refuse(
                principal.describe(), address, action, why_not, ua.StatusCodes.BadInvalidState
            )
        return Admitted(principal.describe(), address, action, payload)

    async def call(
        self, method: Method, args: tuple[Any, ...], gate: Gate | None = None
    ) -> ua.CallMethodResult:
        """Check who calls, then send the command as HTTP does; the answer as a CallMethodResult."""
        admitted = self.admit(method, args, gate)
        if isinstance(admitted, ua.CallMethodResult):
            return admitted
        assert method.command is not None
        who, address, action = admitted.who, admitted.address, admitted.action
        note = AuditNote(who, address, action, _label)
        try:
            outcome = await self.cell.command(
                method.command,
                source=f"opcua:{address}",
                payload=admitted.payload,
                audit=note,
                asked_at_estops=ASKED_AT_ESTOPS.get(),
            )
        except (EventQueueFull, WorkerStopped, JournalUnavailable) as exc:
            return self._refuse(
                who, address, action, str(exc), ua.StatusCodes.BadResourceUnavailable
            )
        code = status_of(outcome)
        if code != ua.StatusCodes.Good:
            log.info("OPC UA %s refused (%s): %s", method.name, status_name(code), outcome.message)
        return answer(
            code, outcome.accepted, outcome.state.value, outcome.message, outcome.event_id
        )

    def audit(self, who: str, address: str, action: str, outcome: str, detail: str) -> None:
        """A row in the audit trail for a call the OPC UA layer answers itself."""
        journal = self.cell.journal
        if journal is not None:
            journal.append([records.audit(time.time(), who, address, action, outcome, detail)])

    def _refuse(
        self,
        who: str,
        address: str,
        action: str,
        why: str,
        code: int = ua.StatusCodes.BadUserAccessDenied,
    ) -> ua.CallMethodResult:
        """A call refused before the cell saw it: audited as the HTTP gate's refusals are."""
        journal = self.cell.journal
        if journal is not None:
            row = records.audit(
                time.time(), who, address, action, f"refused ({status_name(code)})", why
            )
            journal.append([row], durable=False)
        log.info("%s from %s refused: %s", action, address, why)
        return answer(code, False, self.cell.view.state.value, why, "")
