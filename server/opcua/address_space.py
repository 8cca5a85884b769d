"""The cell's nodes: an object named for the cell with Status, Admin, CellState and methods.

Modelled on the PackML companion specification (OPC 30050) as far as a client
reading PackTags needs: Status.StateCurrent, Status.UnitModeCurrent,
Status.StopReason, Admin's counts, OEE and times. The node ids are strings
(`ns=<urn>;s=<cell_id>.Status.StateCurrent`), the same at every start, so a
SCADA configured against them keeps working across restarts. Every variable
is read-only: the cell is commanded through its methods only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from datetime import UTC, datetime

from asyncua import Node, Server, ua

from server.core.machine.transitions import State
from server.opcua.tags import ADMIN_COUNTS, ADMIN_FIGURES

NAMESPACE_URI = "urn:glue-cell:packml"


@dataclass
class CellNodes:
    """The nodes the follower writes, by name."""

    cell: Node
    cell_id: str
    namespace: int
    variables: dict[str, ua.NodeId] = field(default_factory=dict)
    types: dict[str, ua.VariantType] = field(default_factory=dict)


def node_id_of(namespace: int, text: str) -> ua.NodeId:
    """A string node id in the cell's namespace."""
    return ua.NodeId.from_string(f"ns={namespace};s={text}")


async def _variable(
    nodes: CellNodes, parent: Node, path: str, initial: object, kind: ua.VariantType
) -> None:
    name = path.rsplit(".", 1)[-1]
    node_id = node_id_of(nodes.namespace, f"{nodes.cell_id}.{path}")
    node = await parent.add_variable(
        node_id, ua.QualifiedName(name, nodes.namespace), initial, kind
    )
    nodes.variables[path] = node.nodeid
    nodes.types[path] = kind


async def _folder(nodes: CellNodes, parent: Node, path: str) -> Node:
    name = path.rsplit(".", 1)[-1]
    node_id = node_id_of(nodes.namespace, f"{nodes.cell_id}.{path}")
    return await parent.add_object(node_id, ua.QualifiedName(name, nodes.namespace))


async def build(server: Server, cell_id: str) -> CellNodes:
    """Create the cell's object and its variables (methods: server/opcua/methods.py)."""
    namespace = await server.register_namespace(NAMESPACE_URI)
    cell = await server.nodes.objects.add_object(
        node_id_of(namespace, cell_id), ua.QualifiedName(cell_id, namespace)
    )
    nodes = CellNodes(cell, cell_id, namespace)
    Int32, Double, String = ua.VariantType.Int32, ua.VariantType.Double, ua.VariantType.String
    status = await _folder(nodes, cell, "Status")
    await _variable(nodes, status, "Status.StateCurrent", 0, Int32)
    await _variable(nodes, status, "Status.UnitModeCurrent", 0, Int32)
    reason = await _folder(nodes, status, "Status.StopReason")
    await _variable(nodes, reason, "Status.StopReason.ID", "", String)
    await _variable(nodes, reason, "Status.StopReason.Message", "", String)
    await _variable(nodes, reason, "Status.StopReason.Component", "", String)
    await _variable(nodes, status, "Status.CellStateName", "", String)
    admin = await _folder(nodes, cell, "Admin")
    for name, _ in ADMIN_COUNTS:
        await _variable(nodes, admin, f"Admin.{name}", 0, Int32)
    for name, _ in ADMIN_FIGURES:
        await _variable(nodes, admin, f"Admin.{name}", math.nan, Double)
    in_state = await _folder(nodes, admin, "Admin.TimeInState")
    for state in State:
        await _variable(nodes, in_state, f"Admin.TimeInState.{state.value}", 0.0, Double)
    await _variable(nodes, cell, "CellState", "{}", String)
    return nodes


def data_value(kind: ua.VariantType, value: object, at: float | None = None) -> ua.DataValue:
    """A value stamped with when it became true in the cell (`at`, Unix seconds, its
    SourceTimestamp) and when the server took it (ServerTimestamp, now): asyncua stores
    what it is given and fills in neither."""
    stamp = datetime.fromtimestamp(at, UTC) if at is not None else None
    return ua.DataValue(
        ua.Variant(value, kind),
        SourceTimestamp=stamp,  # type: ignore[arg-type]
        ServerTimestamp=datetime.now(UTC),  # type: ignore[arg-type]
    )
