"""The cell's nodes: an OPC 30050 PackMLBaseObjectType instance named for the cell.

The object `<cell_id>` is typed PackMLBaseObjectType (server/opcua/packml_types.py)
and holds, as the standard declares them: Status (mode, supported modes, requested
state, speeds, blocked and starved), Admin (counts as PackMLCountDataType, the stop
reason, alarms and warnings as PackMLAlarmDataType, the state and mode time arrays)
and BaseStateMachine with its nested MachineState and ExecuteState, each with its
CurrentState. Beside them the cell's own: Status.StateCurrent (the 17-state
number, as PackTags read it), Status.CellStateName, Admin's OEE figures and
TimeInState per cell state, and CellState (the JSON document of GET /state).

Every node id is a string in the cell's namespace, the member's path under the
cell (`ns=<urn>;s=<cell_id>.Status.UnitModeCurrent`), the same at every start, so
a SCADA configured against them keeps working across restarts; browse names of the
standard's members are in PackML's namespace, as a PackML client looks them up.
Every variable is read-only: the cell is commanded through its methods only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from datetime import UTC, datetime

from asyncua import Server, ua

from server.core.machine.transitions import State
from server.opcua import packml_model as model
from server.opcua.nodes import add_object, add_property, add_variable, nid
from server.opcua.packml_types import (
    DECLARATIONS,
    STATES_TIMES,
    Kind,
    Member,
    install,
    px,
)
from server.opcua.tags import ADMIN_FIGURES

NAMESPACE_URI = "urn:glue-cell:packml"
# The machines of BaseStateMachine, by the path of each under the cell.
MACHINES = (
    ("BaseStateMachine", model.Level.BASE),
    ("BaseStateMachine.MachineState", model.Level.MACHINE),
    ("BaseStateMachine.MachineState.ExecuteState", model.Level.EXECUTE),
)
# How many alarms and warnings Admin shows at most (AlarmExtent, WarningExtent).
ALARM_EXTENT = 8
MACHINE_SPEED = 1.0  # parts per cycle the cell is built for: one part at a time
NULL_TIME = datetime(1601, 1, 1, tzinfo=UTC)  # OPC UA's null DateTime (no time known)


@dataclass
class MethodPlace:
    """Where a standard method goes: its parent, id and declaration."""

    parent: ua.NodeId
    node_id: ua.NodeId
    member: Member
    path: str


@dataclass
class CellNodes:
    """The nodes the follower writes, by path, and where the methods go."""

    cell: ua.NodeId
    cell_id: str
    namespace: int
    packml: int
    variables: dict[str, ua.NodeId] = field(default_factory=dict)
    types: dict[str, ua.VariantType] = field(default_factory=dict)
    dimensions: dict[str, list[int]] = field(default_factory=dict)
    methods: dict[str, MethodPlace] = field(default_factory=dict)


def node_id_of(namespace: int, text: str) -> ua.NodeId:
    """A string node id in the cell's namespace."""
    return ua.NodeId.from_string(f"ns={namespace};s={text}")


_KINDS = {
    6: ua.VariantType.Int32,
    10: ua.VariantType.Float,
    1: ua.VariantType.Boolean,
    12: ua.VariantType.String,
    17: ua.VariantType.NodeId,
    11: ua.VariantType.Double,
}


def _kind(member: Member) -> ua.VariantType:
    data_type = member.instance_data_type or member.data_type
    assert data_type is not None
    if data_type.namespace:  # PackML's: the mode enumeration is an Int32 on the wire
        return ua.VariantType.Int32 if data_type == px(11) else ua.VariantType.ExtensionObject
    return _KINDS[data_type.id]


def _initial(member: Member, nodes: CellNodes, path: str) -> ua.Variant:
    kind = _kind(member)
    if member.rank == 2:
        dims = [len(model.UnitMode), STATES_TIMES]
        nodes.dimensions[path] = dims
        return ua.Variant([0] * (dims[0] * dims[1]), kind, Dimensions=[ua.Int32(d) for d in dims])
    if member.rank == 1:
        if kind is ua.VariantType.Int32:
            return ua.Variant([0] * len(model.UnitMode), kind)
        return ua.Variant([], kind)
    defaults: dict[ua.VariantType, object] = {
        ua.VariantType.Int32: 0,
        ua.VariantType.Float: 0.0,
        ua.VariantType.Boolean: False,
        ua.VariantType.String: "",
        ua.VariantType.NodeId: ua.NodeId(),
    }
    if kind is ua.VariantType.ExtensionObject:  # the stop reason: none yet
        reason = ua.PackMLAlarmDataType()  # type: ignore[attr-defined]
        reason.DateTime = reason.AckDateTime = NULL_TIME
        return ua.Variant(reason, kind)
    return ua.Variant(defaults[kind], kind)


async def _members(
    server: Server, nodes: CellNodes, parent: ua.NodeId, path: str, type_id: int
) -> None:
    ns, packml = nodes.namespace, nodes.packml
    for member in DECLARATIONS[type_id]:
        child = f"{path}.{member.name}" if path else member.name
        node_id = node_id_of(ns, f"{nodes.cell_id}.{child}")
        name = ua.QualifiedName(member.name, 0 if member.name.startswith("Available") else packml)
        if member.kind is Kind.METHOD:
            nodes.methods[child] = MethodPlace(parent, node_id, member, child)
        elif member.kind is Kind.OBJECT:
            typedef = member.type_definition.node(packml)
            await add_object(server, parent, node_id, name, typedef)
            await _members(server, nodes, node_id, child, member.type_definition.id)
            if member.type_definition.id in (1, 2, 3):
                await _current_state(server, nodes, node_id, child)
        else:
            await _variable(server, nodes, parent, node_id, name, member, child)


async def _variable(
    server: Server,
    nodes: CellNodes,
    parent: ua.NodeId,
    node_id: ua.NodeId,
    name: ua.QualifiedName,
    member: Member,
    path: str,
) -> None:
    packml = nodes.packml
    data_type = (member.instance_data_type or member.data_type or px(0)).node(packml)
    value = _initial(member, nodes, path)
    if member.name == "UnitSupportedModes":
        value = ua.Variant(px(model.MODE_ENUM[1]).node(packml), ua.VariantType.NodeId)
    kind = (
        nid(ua.ObjectIds.HasProperty) if member.kind is Kind.PROPERTY else member.via.node(packml)
    )
    added = await add_variable(
        server,
        parent,
        node_id,
        name,
        value,
        data_type,
        rank=member.rank,
        dimensions=nodes.dimensions.get(path, [0] * member.rank) if member.rank > 0 else None,
        type_definition=member.type_definition.node(packml),
        kind=kind,
    )
    nodes.variables[path], nodes.types[path] = added, _kind(member)
    for prop in member.properties:  # an AnalogItem's EURange: what the speed can be
        await add_property(
            server,
            added,
            node_id_of(nodes.namespace, f"{nodes.cell_id}.{path}.{prop.name}"),
            ua.QualifiedName(prop.name, 0),
            ua.Variant(ua.Range(0.0, MACHINE_SPEED)),
            nid(ua.ObjectIds.Range),
        )


async def _current_state(server: Server, nodes: CellNodes, machine: ua.NodeId, path: str) -> None:
    """A state machine's CurrentState (FiniteStateVariableType): the state's name, its
    node (Id, the standard's state object) and its StateNumber (Number)."""
    ns = nodes.namespace
    here = f"{path}.CurrentState"
    node = await add_variable(
        server,
        machine,
        node_id_of(ns, f"{nodes.cell_id}.{here}"),
        ua.QualifiedName("CurrentState", 0),
        ua.Variant(ua.LocalizedText(""), ua.VariantType.LocalizedText),
        nid(ua.ObjectIds.LocalizedText),
        type_definition=nid(ua.ObjectIds.FiniteStateVariableType),
    )
    nodes.variables[here], nodes.types[here] = node, ua.VariantType.LocalizedText
    for name, kind, data_type, initial in (
        ("Id", ua.VariantType.NodeId, ua.ObjectIds.NodeId, ua.NodeId()),
        ("Number", ua.VariantType.UInt32, ua.ObjectIds.UInt32, 0),
    ):
        prop = await add_property(
            server,
            node,
            node_id_of(ns, f"{nodes.cell_id}.{here}.{name}"),
            ua.QualifiedName(name, 0),
            ua.Variant(initial, kind),
            nid(data_type),
        )
        nodes.variables[f"{here}.{name}"], nodes.types[f"{here}.{name}"] = prop, kind


async def _own(
    server: Server, nodes: CellNodes, path: str, initial: object, kind: ua.VariantType
) -> None:
    """One of the cell's own variables (not the standard's), in the cell's namespace."""
    parent_path, _, name = path.rpartition(".")
    parent = (
        nodes.cell
        if not parent_path
        else node_id_of(nodes.namespace, f"{nodes.cell_id}.{parent_path}")
    )
    data_type = nid(getattr(ua.ObjectIds, kind.name))
    node = await add_variable(
        server,
        parent,
        node_id_of(nodes.namespace, f"{nodes.cell_id}.{path}"),
        ua.QualifiedName(name, nodes.namespace),
        ua.Variant(initial, kind),
        data_type,
    )
    nodes.variables[path], nodes.types[path] = node, kind


async def build(server: Server, cell_id: str) -> CellNodes:
    """PackML's types, then the cell's object and its variables (the methods:
    server/opcua/methods.py and server/opcua/packml_methods.py)."""
    packml = await install(server)
    namespace = await server.register_namespace(NAMESPACE_URI)
    cell = await add_object(
        server,
        server.nodes.objects.nodeid,
        node_id_of(namespace, cell_id),
        ua.QualifiedName(cell_id, namespace),
        nid(model.BASE_OBJECT_TYPE[1], packml),
        kind=nid(ua.ObjectIds.Organizes),
        description=f"the glue cell {cell_id} (OPC 30050 PackML)",
    )
    nodes = CellNodes(cell, cell_id, namespace, packml)
    await _members(server, nodes, cell, "", model.BASE_OBJECT_TYPE[1])
    Int32, Double, String = ua.VariantType.Int32, ua.VariantType.Double, ua.VariantType.String
    await _own(server, nodes, "Status.StateCurrent", 0, Int32)
    await _own(server, nodes, "Status.CellStateName", "", String)
    for name, _ in ADMIN_FIGURES:
        await _own(server, nodes, f"Admin.{name}", math.nan, Double)
    await add_object(
        server,
        node_id_of(namespace, f"{cell_id}.Admin"),
        node_id_of(namespace, f"{cell_id}.Admin.TimeInState"),
        ua.QualifiedName("TimeInState", namespace),
        nid(ua.ObjectIds.FolderType),
    )
    for state in State:
        await _own(server, nodes, f"Admin.TimeInState.{state.value}", 0.0, Double)
    await _own(server, nodes, "CellState", "{}", String)
    return nodes


def data_value(
    kind: ua.VariantType,
    value: object,
    at: float | None = None,
    dimensions: list[int] | None = None,
) -> ua.DataValue:
    """A value stamped with when it became true in the cell (`at`, Unix seconds, its
    SourceTimestamp) and when the server took it (ServerTimestamp, now): asyncua stores
    what it is given and fills in neither."""
    stamp = datetime.fromtimestamp(at, UTC) if at is not None else None
    shape = [ua.Int32(d) for d in dimensions] if dimensions is not None else None
    return ua.DataValue(
        ua.Variant(value, kind, Dimensions=shape),
        SourceTimestamp=stamp,  # type: ignore[arg-type]
        ServerTimestamp=datetime.now(UTC),  # type: ignore[arg-type]
    )
