"""Adding nodes with the ids, type definitions and reference types the cell chooses.

asyncua's own helpers give every node BaseDataVariableType or BaseObjectType, and a
method's InputArguments and OutputArguments numeric ids of its choosing (a new id
at every start when the order of creation changes). The cell's address space
needs its nodes typed from OPC 30050 and every id a stable string, so each node
is added here with an AddNodes item of its own.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from asyncua import Server, ua


def nid(identifier: int | str, namespace: int = 0) -> ua.NodeId:
    """A node id, numeric or string, in `namespace` (asyncua's types spelt out for mypy)."""
    if isinstance(identifier, str):
        return ua.NodeId(ua.String(identifier), ua.Int16(namespace))
    return ua.NodeId(ua.Int32(identifier), ua.Int16(namespace))


HAS_COMPONENT = nid(ua.ObjectIds.HasComponent)
HAS_PROPERTY = nid(ua.ObjectIds.HasProperty)
PROPERTY_TYPE = nid(ua.ObjectIds.PropertyType)
DATA_VARIABLE = nid(ua.ObjectIds.BaseDataVariableType)
MANDATORY = nid(ua.ObjectIds.ModellingRule_Mandatory)
OPTIONAL = nid(ua.ObjectIds.ModellingRule_Optional)
READ = ua.AccessLevel.CurrentRead.mask


def _text(name: str) -> ua.LocalizedText:
    return ua.LocalizedText(name)


async def _added(server: Server, item: ua.AddNodesItem, rule: ua.NodeId | None) -> ua.NodeId:
    (result,) = await server.iserver.isession.add_nodes([item])
    result.StatusCode.check()
    node_id: ua.NodeId = result.AddedNodeId
    if rule is not None:
        await reference(server, node_id, nid(ua.ObjectIds.HasModellingRule), rule)
    return node_id


async def reference(
    server: Server, source: ua.NodeId, kind: ua.NodeId, target: ua.NodeId, forward: bool = True
) -> None:
    """A reference of `kind` from `source` to `target` (and its inverse)."""
    item = ua.AddReferencesItem()
    item.SourceNodeId, item.ReferenceTypeId, item.TargetNodeId = source, kind, target
    item.IsForward = forward
    item.TargetNodeClass = ua.NodeClass.Unspecified
    (status,) = await server.iserver.isession.add_references([item])
    status.check()


async def add_object(
    server: Server,
    parent: ua.NodeId,
    node_id: ua.NodeId,
    name: ua.QualifiedName,
    type_definition: ua.NodeId,
    *,
    kind: ua.NodeId = HAS_COMPONENT,
    rule: ua.NodeId | None = None,
    description: str = "",
) -> ua.NodeId:
    item = ua.AddNodesItem()
    item.RequestedNewNodeId, item.BrowseName, item.ParentNodeId = node_id, name, parent
    item.NodeClass, item.ReferenceTypeId = ua.NodeClass.Object, kind
    item.TypeDefinition = type_definition
    attributes = ua.ObjectAttributes()
    attributes.DisplayName = _text(name.Name)
    if description:
        attributes.Description = _text(description)
    item.NodeAttributes = attributes
    return await _added(server, item, rule)


async def add_variable(
    server: Server,
    parent: ua.NodeId,
    node_id: ua.NodeId,
    name: ua.QualifiedName,
    value: ua.Variant,
    data_type: ua.NodeId,
    *,
    rank: int = ua.ValueRank.Scalar,
    dimensions: Sequence[int] | None = None,
    type_definition: ua.NodeId = DATA_VARIABLE,
    kind: ua.NodeId = HAS_COMPONENT,
    rule: ua.NodeId | None = None,
    description: str = "",
) -> ua.NodeId:
    """A read-only variable (the cell is commanded through its methods only)."""
    item = ua.AddNodesItem()
    item.RequestedNewNodeId, item.BrowseName, item.ParentNodeId = node_id, name, parent
    item.NodeClass, item.ReferenceTypeId = ua.NodeClass.Variable, kind
    item.TypeDefinition = type_definition
    attributes = ua.VariableAttributes()
    attributes.DisplayName = _text(name.Name)
    if description:
        attributes.Description = _text(description)
    attributes.Value, attributes.DataType, attributes.ValueRank = value, data_type, rank
    if dimensions is not None:
        attributes.ArrayDimensions = [ua.UInt32(d) for d in dimensions]
    attributes.AccessLevel = attributes.UserAccessLevel = READ
    attributes.WriteMask = attributes.UserWriteMask = 0
    item.NodeAttributes = attributes
    return await _added(server, item, rule)


async def add_property(
    server: Server,
    parent: ua.NodeId,
    node_id: ua.NodeId,
    name: ua.QualifiedName,
    value: ua.Variant,
    data_type: ua.NodeId,
    *,
    rank: int = ua.ValueRank.Scalar,
    rule: ua.NodeId | None = None,
    description: str = "",
) -> ua.NodeId:
    return await add_variable(
        server,
        parent,
        node_id,
        name,
        value,
        data_type,
        rank=rank,
        dimensions=[0] if rank == ua.ValueRank.OneDimension else None,
        type_definition=PROPERTY_TYPE,
        kind=HAS_PROPERTY,
        rule=rule,
        description=description,
    )


def argument(name: str, data_type: ua.NodeId, rank: int = -1, description: str = "") -> ua.Argument:
    """One method argument."""
    made = ua.Argument()
    made.Name, made.DataType, made.ValueRank = name, data_type, rank
    made.ArrayDimensions = [0] if rank == ua.ValueRank.OneDimension else []
    made.Description = _text(description)
    return made


async def add_method(
    server: Server,
    parent: ua.NodeId,
    node_id: ua.NodeId,
    name: ua.QualifiedName,
    inputs: Sequence[ua.Argument],
    outputs: Sequence[ua.Argument],
    *,
    callback: Callable[..., Any] | None = None,
    rule: ua.NodeId | None = None,
    argument_ids: tuple[ua.NodeId | None, ua.NodeId | None] = (None, None),
    description: str = "",
) -> ua.NodeId:
    """A method with its argument properties. Where `argument_ids` gives none, the
    arguments' ids are the method's string id with `.InputArguments` and
    `.OutputArguments` appended, so they are as stable as the method's."""
    item = ua.AddNodesItem()
    item.RequestedNewNodeId, item.BrowseName, item.ParentNodeId = node_id, name, parent
    item.NodeClass, item.ReferenceTypeId = ua.NodeClass.Method, HAS_COMPONENT
    attributes = ua.MethodAttributes()
    attributes.DisplayName = _text(name.Name)
    if description:
        attributes.Description = _text(description)
    attributes.Executable = attributes.UserExecutable = True
    item.NodeAttributes = attributes
    method = await _added(server, item, rule)
    for label, arguments, given in (
        ("InputArguments", inputs, argument_ids[0]),
        ("OutputArguments", outputs, argument_ids[1]),
    ):
        if not arguments:
            continue
        method_name = str(node_id.Identifier)
        argument_id = given or nid(f"{method_name}.{label}", node_id.NamespaceIndex)
        await add_property(
            server,
            method,
            argument_id,
            ua.QualifiedName(label, 0),
            ua.Variant(list(arguments), ua.VariantType.ExtensionObject),
            nid(ua.ObjectIds.Argument),
            rank=ua.ValueRank.OneDimension,
            rule=MANDATORY if rule is not None else None,
        )
    if callback is not None:
        server.iserver.isession.add_method_callback(method, callback)
    return method
