"""PackML's methods on the cell's state machines: the catalogue's commands, by PackML's names.

Each of OPC 30050's commands the cell carries out is one of the command catalogue's
entries (server/commands/catalogue.py), sent by `CellMethods.call` exactly as the
cell's own methods and HTTP send it: the same role, the same input checks, the same
refusals with the same messages and status codes, the same audit row (action
`OPC UA PackML <name>`). PackML adds one check of its own where its state model is
stricter than the cell's: Start only in Idle (after a Stop or a finished part,
PackML first wants a Reset) and Reset only in Stopped or Complete.

| PackML method (path under the cell)          | Catalogue command |
|----------------------------------------------|-------------------|
| BaseStateMachine.Abort                       | estop             |
| BaseStateMachine.Clear                       | reset             |
| BaseStateMachine.MachineState.Stop           | cancel            |
| ...MachineState.Reset, ...ExecuteState.Reset | (PackML's own)    |
| ...ExecuteState.Start                        | start             |
| ...ExecuteState.Hold / Unhold                | pause / resume    |

PackML's Reset has no counterpart in the cell, which is IDLE both in PackML's
Stopped or Complete and in its Idle: the unit shows Resetting while the cell
confirms every device is connected and without an active fault (a read of the
devices' health, a moment), then Idle. A device not ready refuses the Reset with its
problem (BadInvalidState) and the unit stays where it was: nothing is shown as
Resetting that cannot end in Idle.

SetMachSpeed, SetParameter, SetProduct and SetUnitMode, mandatory in the standard,
are refused with BadNotSupported: the cell's speed is its spray settings,
its product the part on the table, its mode what it is doing.
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Callable
from typing import Any, Final

from asyncua import Server, ua

from server.bootstrap.cell import Cell
from server.commands.catalogue import CATALOGUE
from server.core.machine.transitions import Command, State
from server.opcua.address_space import CellNodes
from server.opcua.methods import OUTPUTS, CellMethods, Method, answer
from server.opcua.nodes import add_method, argument, nid
from server.opcua.packml import PackMLState
from server.opcua.packml_feed import PackMLFeed
from server.security.tokens import Role

log = logging.getLogger(__name__)

_SPEC: Final = {spec.command: spec for spec in CATALOGUE}
_START_ROLE: Final = _SPEC[Command.START].role

# The path of each PackML method under the cell, the command it sends (None: PackML's
# Reset, carried out here) and its description.
PACKML_METHODS: Final = {
    "BaseStateMachine.Abort": (Command.ESTOP, "software stop: valve closed, robot stopped"),
    "BaseStateMachine.Clear": (Command.RESET, "leave Aborted once every device answers"),
    "BaseStateMachine.MachineState.Stop": (Command.CANCEL, "end the operation, glue off"),
    "BaseStateMachine.MachineState.Reset": (None, "Stopped or Complete → Idle"),
    "BaseStateMachine.MachineState.ExecuteState.Start": (Command.START, "find the part, spray"),
    "BaseStateMachine.MachineState.ExecuteState.Hold": (Command.PAUSE, "valve closed, robot still"),
    "BaseStateMachine.MachineState.ExecuteState.Unhold": (Command.RESUME, "continue the run"),
    "BaseStateMachine.MachineState.ExecuteState.Reset": (None, "Stopped or Complete → Idle"),
}
NOT_SUPPORTED: Final = {
    "SetMachSpeed": "the cell's speed is set by its spray settings, not by a machine speed",
    "SetParameter": "the cell takes its parameters from its settings and the part library",
    "SetProduct": "the cell sprays the part it finds on the table (or names, via its Start)",
    "SetUnitMode": "the mode follows what the cell does: Maintenance while calibrating or "
    "teaching a part, else Produce",
}


def method_of(path: str) -> Method:
    """The `Method` a PackML method stands for (its role: the catalogue's)."""
    command, description = PACKML_METHODS[path]
    name = path.rsplit(".", 1)[-1]
    role = _SPEC[command].role if command is not None else _START_ROLE
    return Method(f"PackML {name}", name, command, role, description)


class PackMLMethods:
    """The PackML method callbacks of one cell object."""

    def __init__(self, server: Server, cell: Cell, methods: CellMethods, feed: PackMLFeed) -> None:
        self.server = server
        self.cell = cell
        self.methods = methods
        self.feed = feed

    async def add(self, nodes: CellNodes) -> None:
        """Each standard method the instance has, with its callback (the arguments'
        ids are the method's with `.InputArguments`/`.OutputArguments`)."""
        packml = nodes.packml
        outputs = [argument(name, nid(kind.value)) for name, kind in OUTPUTS]
        for path, place in nodes.methods.items():
            inputs = [argument(n, t.node(packml), r) for n, t, r in place.member.inputs]
            name = ua.QualifiedName(place.member.name, packml)
            if path in PACKML_METHODS:
                method = method_of(path)
                self.methods.nodes[place.node_id] = method
                callback = self._callback(method)
                description = f"PackML {method.packml}: {method.description}"
            else:
                callback = self._unsupported(place.member.name)
                description = f"not supported: {NOT_SUPPORTED[place.member.name]}"
            await add_method(
                self.server,
                place.parent,
                place.node_id,
                name,
                inputs,
                outputs,
                callback=callback,
                description=description,
            )
            if path not in PACKML_METHODS:  # nobody may call it: say so before a call
                for attribute in (ua.AttributeIds.Executable, ua.AttributeIds.UserExecutable):
                    await self.server.write_attribute_value(
                        place.node_id, ua.DataValue(ua.Variant(False)), attribute
                    )

    def _callback(self, method: Method) -> Callable[..., Awaitable[ua.CallMethodResult]]:
        async def call(parent: ua.NodeId, *args: Any) -> ua.CallMethodResult:
            return await self.call(method, args)

        return call

    def _unsupported(self, name: str) -> Callable[..., Awaitable[ua.CallMethodResult]]:
        async def call(parent: ua.NodeId, *args: Any) -> ua.CallMethodResult:
            why = NOT_SUPPORTED[name]
            return answer(ua.StatusCodes.BadNotSupported, False, self._state(), why, "")

        return call

    def _state(self) -> str:
        return self.cell.view.state.value

    async def call(self, method: Method, args: tuple[Any, ...]) -> ua.CallMethodResult:
        """PackML's check of its own state, then the command as every door sends it."""
        if method.command is Command.START:
            parameters = args[0].Value if args and isinstance(args[0], ua.Variant) else None
            if parameters:
                why = (
                    "the cell's Start takes no parameters: it finds the part on the table "
                    "(to spray a named library part, call the cell's own Start(WorkpieceId))"
                )
                admitted = self.methods.admit(method, (), lambda: why)
                assert isinstance(admitted, ua.CallMethodResult)
                admitted.StatusCode = ua.StatusCode(ua.UInt32(ua.StatusCodes.BadInvalidArgument))
                return admitted
            return await self.methods.call(method, (), self._gate_start)
        if method.command is None:
            return await self._reset(method)
        return await self.methods.call(method, (), None)

    def _gate_start(self) -> str | None:
        state = self.feed.tracker.state
        if state is PackMLState.IDLE:
            return None
        hint = "; Reset first" if state in (PackMLState.STOPPED, PackMLState.COMPLETE) else ""
        return f"Start is taken in Idle; the unit is in {state.browse_name}{hint}"

    def _gate_reset(self) -> str | None:
        state = self.feed.tracker.state
        if state not in (PackMLState.STOPPED, PackMLState.COMPLETE):
            hint = "; Clear first" if state is PackMLState.ABORTED else ""
            return (
                f"Reset is taken in Stopped or Complete; the unit is in {state.browse_name}{hint}"
            )
        if self.cell.view.state is not State.IDLE:
            return f"the cell is {self._state()}: Reset waits until it is IDLE"
        missing = not_ready(self.cell.view.health()["devices"])
        if missing:
            device, problem = missing[0]
            return f"{device} is not ready ({problem}): Reset once it is back"
        return None

    async def _reset(self, method: Method) -> ua.CallMethodResult:
        admitted = self.methods.admit(method, (), self._gate_reset)
        if isinstance(admitted, ua.CallMethodResult):
            return admitted
        await self.feed.resetting()
        await self.feed.reset_done()
        message = "every device is connected and without fault: Idle"
        self.methods.audit(admitted.who, admitted.address, admitted.action, "accepted", message)
        return answer(ua.StatusCodes.Good, True, self._state(), message, "")


def not_ready(devices: dict[str, dict[str, Any]]) -> list[tuple[str, str]]:
    """The devices not connected or with an active fault, and what is wrong with each."""
    found = []
    for name, health in devices.items():
        if not health.get("connected"):
            found.append((name, str(health.get("last_error") or "not connected")))
        elif health.get("active_faults"):
            found.append((name, f"active faults {health['active_faults']}"))
    return found


__all__ = ["PACKML_METHODS", "PackMLMethods", "Role", "method_of", "not_ready"]
