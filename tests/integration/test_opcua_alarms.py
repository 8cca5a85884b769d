"""The cell's faults and warnings as OPC UA alarms, through asyncua's own Client against
the served cell: events of alarm condition types on the cell and the Server, acknowledged
and confirmed with the standard methods, audited, cleared when the cell clears."""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path
from typing import Any

from asyncua import Client, ua

from server.opcua.address_space import NAMESPACE_URI
from tests.integration.test_maintenance import seed
from tests.integration.test_opcua import CELL, client, endpoint, make_token
from tests.processes import environment
from tests.rig import SPRAY_DEMO, WAIT_S, Rig, open_rig, run
from tests.serving import free_port

ALARMS = [ua.ObjectIds.TripAlarmType, ua.ObjectIds.OffNormalAlarmType]


class Events:
    """An OPC UA event handler: every notice in the order it came."""

    def __init__(self) -> None:
        self.seen: list[Any] = []
        self.subscription_id = 0

    def event_notification(self, event: Any) -> None:
        self.seen.append(event)

    def of(self, name: str) -> list[Any]:
        return [e for e in self.seen if getattr(e, "ConditionName", None) == name]

    async def next_of(self, name: str, after: int = 0, **fields: Any) -> Any:
        """The first notice of condition `name` past the `after` first ones with `fields`."""
        async with asyncio.timeout(WAIT_S):
            while True:
                for event in self.of(name)[after:]:
                    if all(getattr(event, k, None) == v for k, v in fields.items()):
                        return event
                await asyncio.sleep(0.02)


async def _subscribe(opc: Client, node: Any) -> Events:
    events = Events()
    subscription = await opc.create_subscription(10, events)
    await subscription.subscribe_events(node, ALARMS, queuesize=1000)
    events.subscription_id = subscription.subscription_id
    return events


async def _call(opc: Client, method: int, condition: ua.NodeId, *args: ua.Variant) -> ua.StatusCode:
    request = ua.CallMethodRequest()
    request.ObjectId = condition
    request.MethodId = ua.NodeId(method)
    request.InputArguments = list(args)
    (result,) = await opc.uaclient.call([request])
    return result.StatusCode


async def acknowledge(opc: Client, event: Any, comment: str) -> ua.StatusCode:
    return await _call(
        opc,
        ua.ObjectIds.AcknowledgeableConditionType_Acknowledge,
        event.NodeId,
        ua.Variant(event.EventId, ua.VariantType.ByteString),
        ua.Variant(ua.LocalizedText(comment), ua.VariantType.LocalizedText),
    )


async def confirm(opc: Client, event: Any, comment: str) -> ua.StatusCode:
    return await _call(
        opc,
        ua.ObjectIds.AcknowledgeableConditionType_Confirm,
        event.NodeId,
        ua.Variant(event.EventId, ua.VariantType.ByteString),
        ua.Variant(ua.LocalizedText(comment), ua.VariantType.LocalizedText),
    )


# The condition's variables a client browses and reads (OPC 10000-9's mandatory ones and
# ConfirmedState), each with its data type.
CHILDREN: dict[str, int] = {
    "EnabledState": ua.ObjectIds.LocalizedText,
    "EnabledState/Id": ua.ObjectIds.Boolean,
    "ActiveState": ua.ObjectIds.LocalizedText,
    "ActiveState/Id": ua.ObjectIds.Boolean,
    "AckedState": ua.ObjectIds.LocalizedText,
    "AckedState/Id": ua.ObjectIds.Boolean,
    "ConfirmedState": ua.ObjectIds.LocalizedText,
    "ConfirmedState/Id": ua.ObjectIds.Boolean,
    "Retain": ua.ObjectIds.Boolean,
    "Severity": ua.ObjectIds.UInt16,
    "LastSeverity": ua.ObjectIds.UInt16,
    "Message": ua.ObjectIds.LocalizedText,
    "Time": ua.ObjectIds.UtcTime,
    "SourceName": ua.ObjectIds.String,
    "Quality": ua.ObjectIds.StatusCode,
    "Comment": ua.ObjectIds.LocalizedText,
}


async def read_condition(opc: Client, condition: ua.NodeId) -> dict[str, Any]:
    """Each of CHILDREN's values, found by browse path under the condition's node; its
    data type and its string node id checked on the way."""
    node = opc.get_node(condition)
    values: dict[str, Any] = {}
    for path, data_type in CHILDREN.items():
        child = await node.get_child([f"0:{name}" for name in path.split("/")])
        assert child.nodeid.NodeIdType == ua.NodeIdType.String, (path, child.nodeid)
        assert child.nodeid.Identifier == f"{condition.Identifier}.{path.replace('/', '.')}"
        assert await child.read_data_type() == ua.NodeId(data_type), path
        values[path] = await child.read_value()
    return values


def _same_as(values: dict[str, Any], event: Any) -> None:
    """The node's variables say what the event said."""
    for path in CHILDREN:
        assert values[path] == event.__dict__[path], (path, values[path], event.__dict__[path])


async def _refresh(opc: Client, events: Events) -> ua.StatusCode:
    return await _call(
        opc,
        ua.ObjectIds.ConditionType_ConditionRefresh,
        ua.NodeId(ua.ObjectIds.ConditionType),
        ua.Variant(events.subscription_id, ua.VariantType.UInt32),
    )


async def _audit(rig: Rig) -> list[tuple[str, str, str, str]]:
    audit = (await rig.api.get("/audit", params={"limit": 100})).json()["audit"]
    return [(r["principal"], r["action"], r["outcome"], r["detail"]) for r in audit]


async def test_an_estop_and_a_device_fault_are_alarms_acknowledged_and_cleared(
    tmp_path: Path,
) -> None:
    port = free_port()
    async with open_rig(tmp_path, cell_id=CELL, opcua_endpoint=endpoint(port)) as rig:
        viewer, operator = await make_token(rig, "viewer"), await make_token(rig, "operator")
        maintenance = await make_token(rig, "maintenance")
        async with (
            client(port, operator) as opc,
            client(port, viewer) as looking,
            client(port, maintenance) as fixing,
        ):
            ns = await opc.get_namespace_index(NAMESPACE_URI)
            cell = opc.get_node(f"ns={ns};s={CELL}")
            on_server = await _subscribe(opc, opc.nodes.server)
            on_cell = await _subscribe(opc, cell)

            # The e-stop: a trip alarm, the first-out, on the cell and the Server.
            stopped = await rig.api.post("/estop", json={"reason": "door open"})
            assert stopped.status_code == 202, stopped.text
            raised = await on_server.next_of("EMERGENCY_STOP", Retain=True)
            assert raised.EventType == ua.NodeId(ua.ObjectIds.TripAlarmType)
            assert raised.Severity == 1000
            assert "door open" in raised.Message.Text
            assert raised.SourceNode == cell.nodeid
            assert raised.FirstInGroupFlag is True
            assert (raised.__dict__["ActiveState/Id"], raised.__dict__["AckedState/Id"]) == (
                True,
                False,
            )
            assert raised.NodeId == ua.NodeId.from_string(f"ns={ns};s={CELL}.Alarms.EMERGENCY_STOP")
            on_cell_raised = await on_cell.next_of("EMERGENCY_STOP")
            assert on_cell_raised.EventId == raised.EventId

            # A viewer may not acknowledge; an operator may, with the notice's EventId.
            refused = await acknowledge(looking, raised, "seen")
            assert refused.value == ua.StatusCodes.BadUserAccessDenied
            accepted = await acknowledge(opc, raised, "seen")
            assert accepted.is_good(), accepted
            acked = await on_server.next_of("EMERGENCY_STOP", **{"AckedState/Id": True})
            assert acked.Comment.Text == "seen" and acked.ClientUserId == "plc-operator"
            assert acked.__dict__["ActiveState/Id"] is True and acked.Retain is True
            again = await acknowledge(opc, raised, "seen twice")  # an old EventId
            assert again.value == ua.StatusCodes.BadEventIdUnknown
            # Confirm: the maintenance role, on the acknowledged notice.
            assert (await confirm(opc, acked, "fixed")).value == ua.StatusCodes.BadUserAccessDenied
            assert (await confirm(fixing, acked, "door closed")).is_good()
            await on_server.next_of("EMERGENCY_STOP", **{"ConfirmedState/Id": True})

            # The reset clears it: inactive and, acknowledged, no longer retained.
            assert (await rig.reset()).status_code == 202
            await rig.wait_state("IDLE")
            cleared = await on_server.next_of("EMERGENCY_STOP", **{"ActiveState/Id": False})
            assert cleared.Retain is False

            # A device fault: the dispenser's alarm, from the glue, first-out again.
            rig.glue.set_alarm("NOZZLE_BLOCKED")
            alarm = await on_server.next_of("ALARM", Retain=True)
            assert alarm.EventType == ua.NodeId(ua.ObjectIds.TripAlarmType)
            assert alarm.SourceName == "glue" and alarm.Severity == 800
            assert alarm.FirstInGroupFlag is True
            rig.glue.clear_faults()
            assert (await rig.reset()).status_code == 202
            await rig.wait_state("IDLE")
            # Cleared but not acknowledged: still retained until someone has seen it.
            ended = await on_server.next_of("ALARM", **{"ActiveState/Id": False})
            assert ended.Retain is True
            # A client (re)connecting asks for what is retained: that notice again.
            before, count = len(on_server.of("ALARM")), len(on_server.seen)
            refreshed = await _call(
                opc,
                ua.ObjectIds.ConditionType_ConditionRefresh,
                ua.NodeId(ua.ObjectIds.ConditionType),
                ua.Variant(on_server.subscription_id, ua.VariantType.UInt32),
            )
            assert refreshed.is_good(), refreshed
            assert (await on_server.next_of("ALARM", before)).EventId == ended.EventId
            # Only what is retained: the e-stop, acknowledged and cleared, is not sent. (On
            # a busy machine a halt can outlast the rig's 0.5 s emergency_stop_timeout: its
            # HALT_INCOMPLETE is retained too, and truly so.)
            refreshed_names = [e.ConditionName for e in on_server.seen[count:]]
            assert "ALARM" in refreshed_names and "EMERGENCY_STOP" not in refreshed_names
            assert set(refreshed_names) <= {"ALARM", "HALT_INCOMPLETE"}, refreshed_names
            assert (await acknowledge(opc, ended, "nozzle cleaned")).is_good()
            gone = await on_server.next_of("ALARM", **{"AckedState/Id": True})
            assert gone.Retain is False

        rows = await _audit(rig)
        assert any(
            p.startswith("plc-viewer") and a == "OPC UA Acknowledge" and o.startswith("refused")
            for p, a, o, _ in rows
        ), rows
        assert any(
            p.startswith("plc-operator")
            and a == "OPC UA Acknowledge"
            and o == "accepted"
            and d == "EMERGENCY_STOP: seen"
            for p, a, o, d in rows
        ), rows
        assert any(
            p.startswith("plc-maintenance") and a == "OPC UA Confirm" and o == "accepted"
            for p, a, o, _ in rows
        ), rows


async def test_a_calibration_warning_is_an_alarm_until_a_run_no_longer_raises_it(
    tmp_path: Path,
) -> None:
    port = free_port()
    async with (
        open_rig(tmp_path, cell_id=CELL, opcua_endpoint=endpoint(port)) as rig,
        client(port) as opc,  # anonymous may subscribe
    ):
        events = await _subscribe(opc, opc.nodes.server)
        rig.camera.knock(2.0, 0.0)
        assert (await run(rig, "start", SPRAY_DEMO))["state"] == "IDLE"
        warned = await events.next_of("CALIBRATION_DEGRADING", Retain=True)
        assert warned.EventType == ua.NodeId(ua.ObjectIds.OffNormalAlarmType)
        assert warned.Severity == 400
        assert warned.__dict__["ActiveState/Id"] is True
        assert warned.FirstInGroupFlag is False  # a warning stops nothing
        assert (await rig.state())["state"] == "IDLE"  # the cell runs on
        # The camera put back: the next run no longer raises it, and it clears.
        rig.camera.knock(0.0, 0.0)
        assert (await run(rig, "start", SPRAY_DEMO))["state"] == "IDLE"
        cleared = await events.next_of("CALIBRATION_DEGRADING", **{"ActiveState/Id": False})
        assert cleared.Retain is True  # nobody acknowledged it


async def test_uasubscribe_shows_the_alarms(tmp_path: Path) -> None:
    """asyncua's own command-line tool, as an integrator runs it: `uasubscribe -t event`
    subscribes to the Server object and prints every event it is sent."""
    port = free_port()
    async with open_rig(tmp_path, cell_id=CELL, opcua_endpoint=endpoint(port)) as rig:
        tool = await asyncio.create_subprocess_exec(
            str(Path(sys.executable).parent / "uasubscribe"),
            "-u",
            endpoint(port),
            "-t",
            "event",
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.DEVNULL,
            env=environment({"PYTHONUNBUFFERED": "1"}),
        )
        assert tool.stdout is not None
        try:
            async with asyncio.timeout(WAIT_S):
                while b"Ctr-C" not in await tool.stdout.readline():  # subscribed
                    pass
                stopped = await rig.api.post("/estop", json={"reason": "door open"})
                assert stopped.status_code == 202, stopped.text
                while b"door open" not in (line := await tool.stdout.readline()):
                    assert line, "uasubscribe ended before the alarm came"
        finally:
            tool.terminate()
            await tool.wait()
        assert b"Severity:1000" in line, line
        assert b"EventType:NodeId(Identifier=10751, NamespaceIndex=0" in line, line  # TripAlarmType


async def test_a_condition_node_holds_the_standard_variables_in_step_with_its_events(
    tmp_path: Path,
) -> None:
    port = free_port()
    async with open_rig(tmp_path, cell_id=CELL, opcua_endpoint=endpoint(port)) as rig:
        operator = await make_token(rig, "operator")
        async with client(port, operator) as opc:
            events = await _subscribe(opc, opc.nodes.server)
            assert (await rig.api.post("/estop", json={"reason": "door open"})).status_code == 202
            raised = await events.next_of("EMERGENCY_STOP", Retain=True)
            values = await read_condition(opc, raised.NodeId)
            _same_as(values, raised)
            assert values["ActiveState/Id"] is True and values["AckedState/Id"] is False
            assert values["ActiveState"].Text == "Active"
            assert values["EnabledState/Id"] is True and values["Retain"] is True
            assert values["Severity"] == values["LastSeverity"] == 1000
            assert "door open" in values["Message"].Text
            assert values["Quality"].is_good()
            # The condition's type says what it is, and its node is the event's ConditionId.
            node = opc.get_node(raised.NodeId)
            type_definition = await node.read_type_definition()
            assert type_definition == ua.NodeId(ua.ObjectIds.TripAlarmType)

            assert (await acknowledge(opc, raised, "seen")).is_good()
            acked = await events.next_of("EMERGENCY_STOP", **{"AckedState/Id": True})
            values = await read_condition(opc, raised.NodeId)
            _same_as(values, acked)
            assert values["AckedState"].Text == "Acknowledged"
            assert values["ConfirmedState/Id"] is False and values["Comment"].Text == "seen"

            assert (await rig.reset()).status_code == 202
            await rig.wait_state("IDLE")
            cleared = await events.next_of("EMERGENCY_STOP", **{"ActiveState/Id": False})
            values = await read_condition(opc, raised.NodeId)
            _same_as(values, cleared)
            assert values["ActiveState"].Text == "Inactive" and values["Retain"] is False


async def test_a_maintenance_warning_clears_when_the_item_is_done(tmp_path: Path) -> None:
    """200 parts make the nozzle's cleaning due: an OffNormalAlarm on the cell; the item
    marked done (POST /maintenance/{item}/done) clears it over OPC UA."""
    seed(tmp_path, {"parts": 200.0})
    port = free_port()
    overrides = {"cell_id": CELL, "opcua_endpoint": endpoint(port), "care_check_interval": 0.2}
    async with open_rig(tmp_path, **overrides) as rig:
        operator = await make_token(rig, "operator")
        async with client(port, operator) as opc:
            events = await _subscribe(opc, opc.nodes.server)
            assert (await _refresh(opc, events)).is_good()  # raised before we subscribed?
            due = await events.next_of("MAINTENANCE_DUE", **{"ActiveState/Id": True})
            assert due.EventType == ua.NodeId(ua.ObjectIds.OffNormalAlarmType)
            assert "clean nozzle" in due.Message.Text and due.Retain is True
            assert (await read_condition(opc, due.NodeId))["ActiveState/Id"] is True

            done = await rig.api.post("/maintenance/clean nozzle/done")
            assert done.status_code == 200, done.text
            cleared = await events.next_of("MAINTENANCE_DUE", **{"ActiveState/Id": False})
            assert cleared.Retain is True  # nobody acknowledged it yet
            values = await read_condition(opc, due.NodeId)
            _same_as(values, cleared)
            assert (await acknowledge(opc, cleared, "nozzle cleaned")).is_good()
            gone = await events.next_of("MAINTENANCE_DUE", **{"AckedState/Id": True})
            assert gone.Retain is False
            assert (await read_condition(opc, due.NodeId))["Retain"] is False
            items = (await rig.api.get("/maintenance")).json()["items"]
            assert next(i for i in items if i["name"] == "clean nozzle")["status"] == "ok"
