"""OPC 30050's types in the server's address space, made by the cell's own code.

`install` registers `http://opcfoundation.org/UA/PackML/` and adds, with the
standard's numeric ids (server/opcua/packml_model.py): the reference types
HasAlarm, HasWarning and HasStopReason; the mode enumeration and the alarm, count,
descriptor, ingredients and product structures (with their binary encodings, so a
client decodes them from the server's DataTypeDefinition); the status, admin and
base object types; and the three nested state machine types with their states and
StateNumbers. Each type declares the members the standard marks Mandatory and the
optional ones the cell fills, with the standard's modelling rules.

`DECLARATIONS` is the one list of members: the types are made from it here and the
cell's instance from it in server/opcua/address_space.py.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Final

from asyncua import Server, ua

from server.opcua import packml_model as model
from server.opcua.nodes import (
    MANDATORY,
    OPTIONAL,
    add_method,
    add_object,
    add_property,
    add_variable,
    argument,
    nid,
    reference,
)

HAS_SUBTYPE = nid(ua.ObjectIds.HasSubtype)


class Kind(Enum):
    OBJECT = "object"
    VARIABLE = "variable"
    PROPERTY = "property"
    METHOD = "method"


@dataclass(frozen=True)
class Ref:
    """A node by namespace (0: OPC UA's own, 1: PackML's) and numeric id."""

    namespace: int
    id: int

    def node(self, packml: int) -> ua.NodeId:
        return nid(self.id, packml if self.namespace else 0)


def ua_id(i: int) -> Ref:
    return Ref(0, i)


def px(i: int) -> Ref:
    return Ref(1, i)


INT32, FLOAT, BOOLEAN, STRING, NODE_ID = ua_id(6), ua_id(10), ua_id(1), ua_id(12), ua_id(17)
DATA_VARIABLE, ANALOG_ITEM, RANGE = ua_id(63), ua_id(2368), ua_id(884)
FINITE_STATE_MACHINE, STATE_TYPE = ua_id(2771), ua_id(2307)
HAS_COMPONENT = ua_id(47)
ENUM, COUNT, ALARM, DESCRIPTOR = px(11), px(14), px(15), px(16)


@dataclass(frozen=True)
class Member:
    """A member a type declares: its kind, the standard's id for the declaration, its
    type definition, data type and value rank, whether Mandatory, the reference from
    its parent, its own properties (an AnalogItem's EURange) and, for a method, its
    input arguments with their property's standard id."""

    name: str
    kind: Kind
    type_id: int
    type_definition: Ref = DATA_VARIABLE
    data_type: Ref | None = None
    rank: int = -1
    mandatory: bool = True
    via: Ref = HAS_COMPONENT
    properties: tuple[Member, ...] = ()
    inputs: tuple[tuple[str, Ref, int], ...] = ()
    inputs_id: int | None = None
    instance_data_type: Ref | None = None  # narrower than the declaration's (an enumeration)


# Members the standard inherits from OPC UA's own types: their names are in namespace 0.
UA_NAMES: Final = frozenset({"EURange", "AvailableStates", "AvailableTransitions"})


def _speed(name: str, type_id: int, range_id: int) -> Member:
    eu_range = Member("EURange", Kind.PROPERTY, range_id, ua_id(68), RANGE)
    return Member(name, Kind.VARIABLE, type_id, ANALOG_ITEM, FLOAT, properties=(eu_range,))


def _method(name: str, type_id: int, mandatory: bool = False, **more: object) -> Member:
    return Member(name, Kind.METHOD, type_id, mandatory=mandatory, **more)  # type: ignore[arg-type]


def _states(type_id: int, states: int) -> tuple[Member, ...]:
    return (
        Member("AvailableStates", Kind.VARIABLE, type_id, data_type=NODE_ID, rank=1),
        Member("AvailableTransitions", Kind.VARIABLE, states, data_type=NODE_ID, rank=1),
    )


_, EXECUTE_SM = model.EXECUTE_STATE_MACHINE_TYPE
_, MACHINE_SM = model.MACHINE_STATE_MACHINE_TYPE
_, BASE_SM = model.BASE_STATE_MACHINE_TYPE
_, STATUS = model.STATUS_OBJECT_TYPE
_, ADMIN = model.ADMIN_OBJECT_TYPE
_, BASE_OBJECT = model.BASE_OBJECT_TYPE
MODES_TIMES = len(model.UnitMode)  # the first dimension of the time arrays: the mode
STATES_TIMES = max(model.PackMLState) + 1  # the second: the state number (0 unused)

DECLARATIONS: Final[dict[int, tuple[Member, ...]]] = {
    STATUS: (
        Member("UnitModeCurrent", Kind.VARIABLE, 200, data_type=ua_id(29), instance_data_type=ENUM),
        Member("UnitSupportedModes", Kind.PROPERTY, 193, ua_id(68), NODE_ID),
        Member("StateRequested", Kind.VARIABLE, 209, data_type=INT32, mandatory=False),
        _speed("CurMachSpeed", 232, 233),
        _speed("MachSpeed", 219, 220),
        Member("EquipmentBlocked", Kind.VARIABLE, 211, data_type=BOOLEAN),
        Member("EquipmentStarved", Kind.VARIABLE, 224, data_type=BOOLEAN),
    ),
    ADMIN: (
        Member("ProdProcessedCount", Kind.VARIABLE, 120, data_type=COUNT, rank=1, mandatory=False),
        Member("ProdDefectiveCount", Kind.VARIABLE, 119, data_type=COUNT, rank=1, mandatory=False),
        Member("StateCurrentTime", Kind.VARIABLE, 248, data_type=INT32, rank=2, mandatory=False),
        Member("StateCumulativeTime", Kind.VARIABLE, 249, data_type=INT32, rank=2, mandatory=False),
        Member("ModeCurrentTime", Kind.VARIABLE, 246, data_type=INT32, rank=1, mandatory=False),
        Member("ModeCumulativeTime", Kind.VARIABLE, 247, data_type=INT32, rank=1, mandatory=False),
        Member(
            "StopReason",
            Kind.VARIABLE,
            244,
            data_type=ALARM,
            mandatory=False,
            via=px(model.HAS_STOP_REASON[1]),
        ),
        Member("StopReasonExtent", Kind.VARIABLE, 245, data_type=INT32, mandatory=False),
        Member(
            "Alarm",
            Kind.VARIABLE,
            238,
            data_type=ALARM,
            rank=1,
            mandatory=False,
            via=px(model.HAS_ALARM[1]),
        ),
        Member("AlarmExtent", Kind.VARIABLE, 239, data_type=INT32, mandatory=False),
        Member(
            "Warning",
            Kind.VARIABLE,
            242,
            data_type=ALARM,
            rank=1,
            mandatory=False,
            via=px(model.HAS_WARNING[1]),
        ),
        Member("WarningExtent", Kind.VARIABLE, 243, data_type=INT32, mandatory=False),
        Member("AccTimeSinceReset", Kind.VARIABLE, 252, data_type=INT32, mandatory=False),
        Member("MachDesignSpeed", Kind.VARIABLE, 253, data_type=FLOAT, mandatory=False),
    ),
    EXECUTE_SM: (
        *_states(125, 126),
        _method("Start", 369, inputs=(("Parameter", DESCRIPTOR, 1),), inputs_id=342),
        _method("Hold", 366),
        _method("Unhold", 368),
        _method("Reset", 361),
    ),
    MACHINE_SM: (
        *_states(153, 154),
        Member("ExecuteState", Kind.OBJECT, 56, px(EXECUTE_SM)),
        _method("Stop", 375),
        _method("Reset", 376),
    ),
    BASE_SM: (
        *_states(167, 158),
        Member("MachineState", Kind.OBJECT, 64, px(MACHINE_SM)),
        _method("Abort", 364),
        _method("Clear", 363),
    ),
    BASE_OBJECT: (
        Member("Status", Kind.OBJECT, 87, px(STATUS)),
        Member("Admin", Kind.OBJECT, 73, px(ADMIN)),
        Member("BaseStateMachine", Kind.OBJECT, 88, px(BASE_SM)),
        Member("PackMLVersion", Kind.PROPERTY, 221, ua_id(68), STRING, mandatory=False),
        Member("TagID", Kind.PROPERTY, 218, ua_id(68), STRING, mandatory=False),
        _method(
            "SetMachSpeed", 400, True, inputs=(("RequestedMachineSpeed", FLOAT, -1),), inputs_id=348
        ),
        _method("SetParameter", 402, True, inputs=(("Parameter", DESCRIPTOR, 1),), inputs_id=352),
        _method("SetProduct", 401, True, inputs=(("Product", px(18), 1),), inputs_id=349),
        _method("SetUnitMode", 362, True, inputs=(("RequestedMode", INT32, -1),), inputs_id=118),
    ),
}
# Each object type: its standard (name, id) and its supertype.
OBJECT_TYPES: Final = (
    (model.STATUS_OBJECT_TYPE, ua_id(58)),
    (model.ADMIN_OBJECT_TYPE, ua_id(58)),
    (model.EXECUTE_STATE_MACHINE_TYPE, FINITE_STATE_MACHINE),
    (model.MACHINE_STATE_MACHINE_TYPE, FINITE_STATE_MACHINE),
    (model.BASE_STATE_MACHINE_TYPE, FINITE_STATE_MACHINE),
    (model.BASE_OBJECT_TYPE, ua_id(58)),
)
# Where each state object lives and its StateNumber property's id.
STATE_OWNER: Final = {
    model.Level.EXECUTE: EXECUTE_SM,
    model.Level.MACHINE: MACHINE_SM,
    model.Level.BASE: BASE_SM,
}
STATE_NUMBER_IDS: Final = {
    27: 127, 28: 128, 29: 129, 30: 130, 31: 131, 32: 132, 33: 133, 34: 134, 35: 135,
    36: 136, 37: 137, 38: 138, 53: 155, 54: 156, 55: 157, 75: 171, 61: 168, 62: 169,
    71: 178,
}  # fmt: skip
# The structures: (name, id, encoding id, fields as (name, data type, value rank)).
EU_INFORMATION, UTC_TIME = ua_id(887), ua_id(294)
STRUCTURES: Final = (
    (model.DESCRIPTOR_DATA_TYPE[0], 16, 77,
     (("ID", INT32, -1), ("Name", STRING, -1), ("Unit", EU_INFORMATION, -1), ("Value", FLOAT, -1))),
    ("PackMLIngredientsDataType", 17, 79,
     (("IngredientID", INT32, -1), ("Parameter", DESCRIPTOR, 1))),
    ("PackMLProductDataType", 18, 81,
     (("ProductID", INT32, -1), ("ProcessVariables", DESCRIPTOR, 1), ("Ingredients", px(17), 1))),
    (model.COUNT_DATA_TYPE[0], 14, 69,
     (("ID", INT32, -1), ("Name", STRING, -1), ("Unit", EU_INFORMATION, -1), ("Count", INT32, -1),
      ("AccCount", INT32, -1))),
    (model.ALARM_DATA_TYPE[0], 15, 74,
     (("ID", INT32, -1), ("Value", INT32, -1), ("Message", STRING, -1), ("Category", INT32, -1),
      ("DateTime", UTC_TIME, -1), ("AckDateTime", UTC_TIME, -1), ("Trigger", BOOLEAN, -1))),
)  # fmt: skip


def _q(name: str, namespace: int) -> ua.QualifiedName:
    return ua.QualifiedName(name, namespace)


async def _reference_types(server: Server, ns: int) -> None:
    for name, type_id, inverse in (model.HAS_ALARM, model.HAS_WARNING, model.HAS_STOP_REASON):
        item = ua.AddNodesItem()
        item.RequestedNewNodeId, item.BrowseName = nid(type_id, ns), _q(name, ns)
        item.NodeClass, item.ReferenceTypeId = ua.NodeClass.ReferenceType, HAS_SUBTYPE
        item.ParentNodeId = nid(ua.ObjectIds.HasComponent)
        attributes = ua.ReferenceTypeAttributes()
        attributes.DisplayName = ua.LocalizedText(name)
        attributes.InverseName = ua.LocalizedText(inverse)
        attributes.IsAbstract, attributes.Symmetric = False, False
        item.NodeAttributes = attributes
        (result,) = await server.iserver.isession.add_nodes([item])
        result.StatusCode.check()


async def _data_type(server: Server, ns: int, name: str, type_id: int, parent: int) -> ua.NodeId:
    item = ua.AddNodesItem()
    item.RequestedNewNodeId, item.BrowseName = nid(type_id, ns), _q(name, ns)
    item.NodeClass, item.ReferenceTypeId = ua.NodeClass.DataType, HAS_SUBTYPE
    item.ParentNodeId = nid(parent)
    attributes = ua.DataTypeAttributes()
    attributes.DisplayName = ua.LocalizedText(name)
    item.NodeAttributes = attributes
    (result,) = await server.iserver.isession.add_nodes([item])
    result.StatusCode.check()
    return nid(type_id, ns)


async def _data_types(server: Server, ns: int) -> None:
    name, enum_id = model.MODE_ENUM
    enum = await _data_type(server, ns, name, enum_id, ua.ObjectIds.Enumeration)
    definition = ua.EnumDefinition()
    values = []
    for mode in model.UnitMode:
        field = ua.EnumField()
        field.Name, field.Value = mode.browse_name, int(mode)
        field.DisplayName = field.Description = ua.LocalizedText(mode.browse_name)
        definition.Fields.append(field)
        value = ua.EnumValueType()
        value.Value, value.DisplayName = int(mode), ua.LocalizedText(mode.browse_name)
        values.append(value)
    await server.write_attribute_value(
        enum, ua.DataValue(ua.Variant(definition)), ua.AttributeIds.DataTypeDefinition
    )
    await add_property(
        server,
        enum,
        nid(194, ns),
        ua.QualifiedName("EnumValues", 0),
        ua.Variant(values, ua.VariantType.ExtensionObject),
        nid(ua.ObjectIds.EnumValueType),
        rank=ua.ValueRank.OneDimension,
    )
    for name, type_id, encoding_id, fields in STRUCTURES:
        structure = await _data_type(server, ns, name, type_id, ua.ObjectIds.Structure)
        encoding = await add_object(
            server,
            structure,
            nid(encoding_id, ns),
            ua.QualifiedName("Default Binary", 0),
            nid(ua.ObjectIds.DataTypeEncodingType),
            kind=nid(ua.ObjectIds.HasEncoding),
        )
        sdef = ua.StructureDefinition()
        sdef.BaseDataType = nid(ua.ObjectIds.Structure)
        sdef.StructureType = ua.StructureType.Structure
        sdef.DefaultEncodingId = encoding
        for field_name, data_type, rank in fields:
            member = ua.StructureField()
            member.Name, member.DataType, member.ValueRank = field_name, data_type.node(ns), rank
            member.IsOptional = False  # asyncua's default is True: every field is present
            member.ArrayDimensions = [ua.UInt32(0)] if rank == 1 else []
            sdef.Fields.append(member)
        await server.write_attribute_value(
            structure, ua.DataValue(ua.Variant(sdef)), ua.AttributeIds.DataTypeDefinition
        )


def default_value(member: Member, ns: int) -> ua.Variant:
    """A member's value before the cell writes one: null of its type, empty arrays."""
    if member.rank >= 1:
        return ua.Variant([], ua.VariantType.Null)
    return ua.Variant(None, ua.VariantType.Null)


async def _declare(server: Server, ns: int, parent: ua.NodeId, member: Member) -> None:
    node_id = nid(member.type_id, ns)
    rule = MANDATORY if member.mandatory else OPTIONAL
    name = _q(member.name, 0 if member.name in UA_NAMES else ns)
    if member.kind is Kind.OBJECT:
        await add_object(server, parent, node_id, name, member.type_definition.node(ns), rule=rule)
    elif member.kind is Kind.METHOD:
        inputs = [argument(n, t.node(ns), r) for n, t, r in member.inputs]
        given = nid(member.inputs_id, ns) if member.inputs_id is not None else None
        await add_method(
            server, parent, node_id, name, inputs, [], rule=rule, argument_ids=(given, None)
        )
    else:
        assert member.data_type is not None
        added = await add_variable(
            server,
            parent,
            node_id,
            name,
            default_value(member, ns),
            member.data_type.node(ns),
            rank=member.rank,
            dimensions=[0] * member.rank if member.rank > 0 else None,
            type_definition=member.type_definition.node(ns),
            kind=(ua_id(46) if member.kind is Kind.PROPERTY else member.via).node(ns),
            rule=rule,
        )
        for prop in member.properties:
            await _declare(server, ns, added, prop)


async def _object_types(server: Server, ns: int) -> None:
    for (name, type_id), supertype in OBJECT_TYPES:
        item = ua.AddNodesItem()
        item.RequestedNewNodeId, item.BrowseName = nid(type_id, ns), _q(name, ns)
        item.NodeClass, item.ReferenceTypeId = ua.NodeClass.ObjectType, HAS_SUBTYPE
        item.ParentNodeId = supertype.node(ns)
        attributes = ua.ObjectTypeAttributes()
        attributes.DisplayName, attributes.IsAbstract = ua.LocalizedText(name), False
        item.NodeAttributes = attributes
        (result,) = await server.iserver.isession.add_nodes([item])
        result.StatusCode.check()
        for member in DECLARATIONS[type_id]:
            await _declare(server, ns, nid(type_id, ns), member)
    for state in model.STATE_NODES:
        owner = nid(STATE_OWNER[state.level], ns)
        node = await add_object(
            server, owner, nid(state.node_id, ns), _q(state.name, ns), STATE_TYPE.node(ns)
        )
        await add_property(
            server,
            node,
            nid(STATE_NUMBER_IDS[state.node_id], ns),
            ua.QualifiedName("StateNumber", 0),
            ua.Variant(state.number, ua.VariantType.UInt32),
            nid(ua.ObjectIds.UInt32),
        )


async def install(server: Server) -> int:
    """Register PackML's namespace and add its types; its namespace index."""
    ns = await server.register_namespace(model.NAMESPACE_URI)
    await _reference_types(server, ns)
    await _data_types(server, ns)
    await _object_types(server, ns)
    await server.load_data_type_definitions()
    return ns


__all__ = ["DECLARATIONS", "Kind", "Member", "install", "px", "reference", "ua_id"]
