"""The alarm conditions' nodes: each an instance of its type a client browses and reads.

A condition's node `<cell_id>.Alarms.<CODE>` (its ConditionId) is instantiated from its
type (TripAlarmType or OffNormalAlarmType) with asyncua's `instantiate`, which makes the
type's mandatory children with string node ids below the condition's own
(`<cell_id>.Alarms.<CODE>.ActiveState.Id`), the standard's browse names, type
definitions and data types: EnabledState, ActiveState and AckedState with their Id,
Retain, Severity, LastSeverity, Message, Time, SourceName, Quality, Comment and the rest
of ConditionType's and BaseEventType's. ConfirmedState (with its Id) is optional in
AcknowledgeableConditionType; the cell serves Confirm, so it is made too. The optional
rest (shelving, suppression, audible sound...) describes what the cell does not do and
is left out.

Every notice the cell emits for a condition is first written into its node's variables,
field by field from the event itself (`write`), so a client that reads the node after
an event sees what the event said, and one that only reads (no subscription) sees the
condition as it is now. The Acknowledge and Confirm methods instantiated under a
condition are linked to the same handlers as the type's (AcknowledgeableConditionType's
Acknowledge and Confirm), so a client may call either.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any, Final

from asyncua import Node, Server, ua
from asyncua.common.instantiate_util import instantiate
from asyncua.common.ua_utils import data_type_to_variant_type

from server.opcua.address_space import data_value

Handler = Callable[..., Awaitable[ua.StatusCode]]


def _node(number: int) -> ua.NodeId:
    return ua.NodeId(ua.Int32(number))


HAS_CONDITION: Final = _node(ua.ObjectIds.HasCondition)
TWO_STATE: Final = _node(ua.ObjectIds.TwoStateVariableType)


@dataclass
class ConditionNode:
    """One condition's node and its variables: each by its event field's name
    ("ActiveState/Id"), with the variant type its data type takes."""

    node_id: ua.NodeId
    variables: dict[str, tuple[ua.NodeId, ua.VariantType]] = field(default_factory=dict)


class ConditionNodes:
    """Makes the conditions' nodes and keeps their variables in step with their events."""

    def __init__(self, server: Server, methods: dict[str, Handler]) -> None:
        self.server = server
        self.methods = methods  # "Acknowledge", "Confirm": the handler of each
        self.made: dict[str, ConditionNode] = {}

    async def make(
        self,
        code: str,
        node_id: ua.NodeId,
        type_id: int,
        folder: ua.NodeId,
        source: ua.NodeId,
        description: str,
    ) -> ConditionNode:
        """The condition's node under `folder`, referenced by `source` (HasCondition);
        `node_id` a string node id, below which its children's ids are made."""
        server = self.server
        base = node_id.Identifier
        assert isinstance(base, str), node_id
        made = await instantiate(
            server.get_node(folder),
            server.get_node(_node(type_id)),
            nodeid=node_id,
            bname=ua.QualifiedName(code, node_id.NamespaceIndex),
            dname=ua.LocalizedText(code),
            instantiate_optional=False,
        )
        condition = server.get_node(node_id)
        made += await instantiate(
            condition,
            server.get_node(TWO_STATE),
            nodeid=ua.NodeId.from_string(f"ns={node_id.NamespaceIndex};s={base}.ConfirmedState"),
            bname=ua.QualifiedName("ConfirmedState", 0),
            instantiate_optional=False,
        )
        await server.write_attribute_value(
            node_id,
            ua.DataValue(ua.Variant(ua.LocalizedText(description), ua.VariantType.LocalizedText)),
            ua.AttributeIds.Description,
        )
        reference = ua.AddReferencesItem()
        reference.SourceNodeId = source
        reference.ReferenceTypeId = HAS_CONDITION
        reference.IsForward = True
        reference.TargetNodeId = node_id
        reference.TargetNodeClass = ua.NodeClass.Object
        await server.iserver.isession.add_references([reference])
        entry = ConditionNode(node_id)
        prefix = f"{base}."
        for node in made:
            if not isinstance(node.nodeid.Identifier, str) or node.nodeid == node_id:
                continue
            path = node.nodeid.Identifier.removeprefix(prefix).replace(".", "/")
            node_class = await node.read_node_class()
            if node_class == ua.NodeClass.Variable:
                entry.variables[path] = (node.nodeid, await self._variant_type(node))
            elif node_class == ua.NodeClass.Method and path in self.methods:
                server.link_method(node, self.methods[path])
        self.made[code] = entry
        return entry

    async def _variant_type(self, node: Node) -> ua.VariantType:
        data_type = self.server.get_node(await node.read_data_type())
        return await data_type_to_variant_type(data_type)

    async def write(self, code: str, event: Any, at: float | None) -> None:
        """Each of the condition's variables from the event's field of the same name."""
        entry = self.made[code]
        fields = vars(event)
        for path, (node_id, kind) in entry.variables.items():
            value = fields.get(path)
            if value is None:
                continue
            if path == "EventType" and isinstance(value, int):
                value = _node(value)
            await self.server.write_attribute_value(node_id, data_value(kind, value, at))
