"""The cell as a PackML client sees it: OPC 30050 checked against the standard's own model.

A real server on loopback with the robot and glue simulators, read and commanded
through asyncua's Client. The browse is checked against the published NodeSet
(tests/reference/packml/): every member the standard marks Mandatory on the types
the cell's instance uses, with the right node class, type definition and data type.
The cycle is driven by a client that knows only PackML: its methods by their
standard browse names and its state numbers from the NodeSet, over a whole day
(start, complete, reset, hold, unhold, stop, abort, clear), checking that every
state change it sees is one the standard's transition table allows.
"""

from __future__ import annotations

import asyncio
import itertools
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from asyncua import Client, Node, ua

from server.opcua.address_space import NAMESPACE_URI
from tests import packml_reference as reference
from tests.rig import WAIT_S, Rig, open_rig
from tests.serving import free_port

CELL = "cell-p"
PACKML = "http://opcfoundation.org/UA/PackML/"
NUMBER = reference.state_numbers()  # "Execute" → 6, as the standard numbers them


def endpoint(port: int) -> str:
    return f"opc.tcp://127.0.0.1:{port}"


async def token(rig: Rig, role: str) -> str:
    created = await rig.api.post("/tokens", json={"name": f"packml-{role}", "role": role})
    assert created.status_code == 201, created.text
    return str(created.json()["token"])


def client(port: int, secret: str | None = None) -> Client:
    opc = Client(endpoint(port), timeout=WAIT_S)
    if secret is not None:
        opc.set_user("packml")
        opc.set_password(secret)
    return opc


async def child(node: Node, name: str, namespace: int) -> Node:
    return await node.get_child(ua.QualifiedName(name, namespace))


async def _is_subtype(opc: Client, data_type: ua.NodeId, of: ua.NodeId) -> bool:
    node = opc.get_node(data_type)
    while True:
        if node.nodeid == of:
            return True
        parents = await node.get_references(ua.ObjectIds.HasSubtype, ua.BrowseDirection.Inverse)
        if not parents:
            return False
        node = opc.get_node(parents[0].NodeId)


def _expected_id(text: str, packml: int) -> ua.NodeId:
    """A NodeSet id ("i=63", "ns=1;i=4", an alias) as the served server numbers it."""
    resolved = ua.NodeId.from_string(reference.resolve(text))
    if resolved.NamespaceIndex == 1:
        return ua.NodeId(resolved.Identifier, packml)
    return resolved


async def _check_type(opc: Client, instance: Node, type_name: str, packml: int) -> list[str]:
    """Every mandatory member of `type_name` under `instance`, as the NodeSet declares it."""
    checked = []
    for member in reference.members(type_name):
        if not member.mandatory:
            continue
        namespace = packml if member.name not in ("AvailableStates", "AvailableTransitions") else 0
        found = await child(instance, member.name, namespace)
        checked.append(f"{type_name}.{member.name}")
        assert (await found.read_node_class()).name == member.node_class, member
        if member.type_definition is not None:
            assert await found.read_type_definition() == _expected_id(
                member.type_definition, packml
            ), member
        if member.data_type is not None:
            served = await found.read_data_type()
            wanted = _expected_id(member.data_type, packml)
            assert served == wanted or await _is_subtype(opc, served, wanted), member
    return checked


async def _subtree_ids(node: Node, into: set[str]) -> None:
    for reference_ in await node.get_references(
        ua.ObjectIds.HierarchicalReferences, ua.BrowseDirection.Forward
    ):
        target = reference_.NodeId
        if reference_.ReferenceTypeId == ua.NodeId(ua.ObjectIds.HasTypeDefinition):
            continue
        text = target.to_string()
        if text in into or target.NamespaceIndex == 0:
            continue
        into.add(text)
        await _subtree_ids(Node(node.session, target), into)


async def test_a_browse_has_every_member_the_standard_makes_mandatory(tmp_path: Path) -> None:
    port = free_port()
    overrides = {"cell_id": CELL, "opcua_endpoint": endpoint(port)}
    served_ids: list[set[str]] = []
    for _ in range(2):  # the second start: the same ids (a SCADA's configuration holds)
        async with open_rig(tmp_path, **overrides) as rig:
            operator, viewer = await token(rig, "operator"), await token(rig, "viewer")
            async with client(port) as opc:
                assert PACKML in await opc.get_namespace_array()
                packml = await opc.get_namespace_index(PACKML)
                ns = await opc.get_namespace_index(NAMESPACE_URI)
                cell = opc.get_node(f"ns={ns};s={CELL}")
                assert await cell.read_type_definition() == ua.NodeId(6, packml)
                checked = await _check_type(opc, cell, "PackMLBaseObjectType", packml)
                status = await child(cell, "Status", packml)
                checked += await _check_type(opc, status, "PackMLStatusObjectType", packml)
                admin = await child(cell, "Admin", packml)
                checked += await _check_type(opc, admin, "PackMLAdminObjectType", packml)
                base = await child(cell, "BaseStateMachine", packml)
                machine = await child(base, "MachineState", packml)
                execute = await child(machine, "ExecuteState", packml)
                for node, name in (
                    (base, "PackMLBaseStateMachineType"),
                    (machine, "PackMLMachineStateMachineType"),
                    (execute, "PackMLExecuteStateMachineType"),
                ):
                    checked += await _check_type(opc, node, name, packml)
                    # FiniteStateMachineType's CurrentState, with its state's Id and Number.
                    current = await child(node, "CurrentState", 0)
                    assert await current.read_type_definition() == ua.NodeId(
                        ua.ObjectIds.FiniteStateVariableType
                    )
                    assert await current.read_data_type() == ua.NodeId(ua.ObjectIds.LocalizedText)
                    await child(current, "Id", 0)
                assert len(checked) >= 20, checked
                # Idle, as the three machines say it: Cleared / Running / Idle.
                names = [
                    (await (await child(n, "CurrentState", 0)).read_value()).Text
                    for n in (base, machine, execute)
                ]
                assert names == ["Cleared", "Running", "Idle"]
                number = await child(await child(execute, "CurrentState", 0), "Number", 0)
                assert await number.read_value() == NUMBER["Idle"]
                mode = await child(status, "UnitModeCurrent", packml)
                assert await mode.read_value() == 1  # Produce
                # The stop reason, alarms and warnings: PackMLAlarmDataType, under Admin.
                alarm_type = ua.NodeId(15, packml)
                for name in ("StopReason", "Alarm", "Warning"):
                    assert await (await child(admin, name, packml)).read_data_type() == alarm_type
                counted = await child(admin, "ProdProcessedCount", packml)
                assert await counted.read_data_type() == ua.NodeId(14, packml)

                # Every node of the cell has a string id, method arguments included.
                ids: set[str] = set()
                await _subtree_ids(cell, ids)
                assert ids and all(";s=" in i for i in ids if i.startswith(f"ns={ns};")), ids
                assert f"ns={ns};s={CELL}.Start.InputArguments" in ids
                assert f"ns={ns};s={CELL}.Start.OutputArguments" in ids
                served_ids.append(ids)

            # Each session is told what it may call: anonymous nothing, a viewer the stop.
            start_path = f"ns={ns};s={CELL}.BaseStateMachine.MachineState.ExecuteState.Start"
            abort_path = f"ns={ns};s={CELL}.BaseStateMachine.Abort"
            set_mode = f"ns={ns};s={CELL}.SetUnitMode"
            for secret, may_start, may_abort in (
                (None, False, False),
                (viewer, False, True),
                (operator, True, True),
            ):
                async with client(port, secret) as opc:
                    start = opc.get_node(start_path)
                    assert await start.read_attribute(ua.AttributeIds.Executable)
                    user = ua.AttributeIds.UserExecutable
                    assert (await start.read_attribute(user)).Value.Value is may_start
                    abort = opc.get_node(abort_path)
                    assert (await abort.read_attribute(user)).Value.Value is may_abort
                    unsupported = opc.get_node(set_mode)
                    executable = await unsupported.read_attribute(ua.AttributeIds.Executable)
                    assert executable.Value.Value is False
    assert served_ids[0] == served_ids[1]


class States:
    """Status.StateCurrent as a subscription delivers it: every change, in order."""

    def __init__(self) -> None:
        self.seen: list[int] = []
        self.changed = asyncio.Event()

    def datachange_notification(self, node: Any, value: Any, data: Any) -> None:
        if not self.seen or self.seen[-1] != value:
            self.seen.append(value)
        self.changed.set()

    async def reach(self, name: str, timeout: float = WAIT_S) -> None:
        async with asyncio.timeout(timeout):
            while not self.seen or self.seen[-1] != NUMBER[name]:
                self.changed.clear()
                await self.changed.wait()


async def test_a_packml_only_client_runs_a_whole_day(tmp_path: Path) -> None:
    port = free_port()
    overrides = {"cell_id": CELL, "opcua_endpoint": endpoint(port)}
    async with open_rig(tmp_path, robot_speed_factor=1, **overrides) as rig:
        secret = await token(rig, "maintenance")  # Clear is the cell's reset: maintenance
        async with client(port, secret) as opc:
            packml = await opc.get_namespace_index(PACKML)
            ns = await opc.get_namespace_index(NAMESPACE_URI)
            cell = opc.get_node(f"ns={ns};s={CELL}")
            status = await child(cell, "Status", packml)
            base = await child(cell, "BaseStateMachine", packml)
            machine = await child(base, "MachineState", packml)
            execute = await child(machine, "ExecuteState", packml)
            states = States()
            subscription = await opc.create_subscription(5, states)
            await subscription.subscribe_data_change(
                await child(status, "StateCurrent", ns), queuesize=1000
            )

            async def call(owner: Node, name: str, *args: Any) -> None:
                method = await child(owner, name, packml)
                await owner.call_method(method, *args)

            async def refused(owner: Node, name: str, *args: Any) -> ua.StatusCode:
                request = ua.CallMethodRequest()
                request.ObjectId = owner.nodeid
                request.MethodId = (await child(owner, name, packml)).nodeid
                request.InputArguments = list(args)
                (result,) = await opc.uaclient.call([request])
                assert not result.StatusCode.is_good(), result
                return result.StatusCode

            no_parameters = ua.Variant([], ua.VariantType.ExtensionObject)
            start: Callable[[], Awaitable[None]] = lambda: call(execute, "Start", no_parameters)  # noqa: E731
            await states.reach("Idle")
            # A part from start to finish: Starting while the part is found and the arm
            # approaches, Execute while it sprays, Completing as the run ends, Complete.
            await start()
            await states.reach("Complete", timeout=WAIT_S * 4)
            # PackML wants a Reset before the next Start, and refuses the Start until then.
            code = await refused(execute, "Start", no_parameters)
            assert code.value == ua.StatusCodes.BadInvalidState
            await call(machine, "Reset")
            await states.reach("Idle")
            # Hold and Unhold while it sprays, then Stop.
            await start()
            await states.reach("Execute", timeout=WAIT_S * 2)
            await call(execute, "Hold")
            await states.reach("Held")
            await call(execute, "Unhold")
            await states.reach("Execute")
            await call(machine, "Stop")
            await states.reach("Stopped")
            await call(machine, "Reset")
            await states.reach("Idle")
            # Abort and Clear: the cell's e-stop and reset.
            await call(base, "Abort")
            await states.reach("Aborted")
            assert (await rig.state())["state"] == "ERROR"
            await call(base, "Clear")
            await states.reach("Stopped")
            await call(machine, "Reset")
            await states.reach("Idle")

    seen = states.seen
    wrong = [(a, b) for a, b in itertools.pairwise(seen) if (a, b) not in reference.allowed()]
    assert not wrong, (wrong, seen)
    for name in (
        "Starting", "Execute", "Completing", "Complete", "Resetting", "Holding", "Held",
        "Unholding", "Stopping", "Stopped", "Aborting", "Aborted", "Clearing",
    ):  # fmt: skip
        assert NUMBER[name] in seen, (name, seen)
