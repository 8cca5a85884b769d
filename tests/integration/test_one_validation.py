"""One validation for every transport: the same bad inputs over HTTP, MQTT and OPC UA,
each refused alike by the HTTP route's own model, with the same field named, the same
detail in the answer and in the audit trail, nothing moved and nothing kept.

A real cell with the robot and glue simulators, Debian's mosquitto, and asyncua's own
Client on the cell's OPC UA endpoint. OPC UA's status for HTTP's 422 is
BadInvalidArgument, with the 422's detail as the method's Message; a request too large
to be read is HTTP's 413 and OPC UA's BadRequestTooLarge. MQTT has no cap of its own
on a message's size (the broker's `message_size_limit` is that), so a 5 MB id there
is read and refused by the model, naming the field; nothing of it is kept either way.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import uuid
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiomqtt
import pytest
from asyncua import Client, ua
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from clients.client.mqtt_signing import sign_command
from server.opcua.address_space import NAMESPACE_URI
from tests.integration.test_opcua import CELL, endpoint, make_token
from tests.mosquitto import login_of, mosquitto
from tests.rig import WAIT_S, Rig, open_rig
from tests.serving import free_port

BASE = f"glue/{CELL}"
FIVE_MB = "a" * (5 * 1024 * 1024)
# Each bad workpiece id: what HTTP refuses with 422 naming `workpiece_id`.
BAD_IDS: dict[str, Any] = {
    "traversal": "../../etc/passwd",
    "bidi-and-line-break": "evil\u202e\nname",
    "nul": "demo\x00",
    "nan": math.nan,
    "infinity": math.inf,
}
START = "POST /start"
OPC_START = "OPC UA Start"
MQTT_START = f"MQTT {BASE}/command/start"


def _json(body: Any) -> bytes:
    """JSON as Python writes it: NaN and Infinity as the bare words a careless sender uses."""
    return json.dumps(body).encode()


class MqttRequester:
    """A plant client sending signed commands to the cell over MQTT v5, one answer per
    request, on a response topic the shipped ACL lets an operator read."""

    def __init__(self, client: aiomqtt.Client) -> None:
        self.client = client
        self.reply_to = f"{BASE}/response/{uuid.uuid4().hex}"

    async def subscribe(self) -> None:
        await self.client.subscribe(self.reply_to, qos=1)

    async def command(self, name: str, token: str, body: dict[str, Any]) -> dict[str, Any]:
        correlation = uuid.uuid4().bytes
        properties = Properties(PacketTypes.PUBLISH)  # type: ignore[no-untyped-call]
        properties.ResponseTopic = self.reply_to
        properties.CorrelationData = correlation
        topic = f"{BASE}/command/{name}"
        message = sign_command(token, topic, body)
        await self.client.publish(topic, _json(message), qos=1, properties=properties)
        async with asyncio.timeout(WAIT_S):
            async for answer in self.client.messages:
                assert answer.properties.CorrelationData == correlation  # type: ignore[union-attr]
                decoded: dict[str, Any] = json.loads(bytes(answer.payload))  # type: ignore[arg-type]
                return decoded
        raise AssertionError("no answer over MQTT")


@contextlib.asynccontextmanager
async def cell_on_three_doors(
    broker_dir: Path, data: Path, opcua_port: int
) -> AsyncIterator[tuple[Rig, MqttRequester]]:
    """A cell served over HTTP, OPC UA on `opcua_port` and MQTT commands through a
    mosquitto of its own, with an operator's MQTT requester linked and listening."""
    with mosquitto(broker_dir) as broker:
        overrides = {
            "cell_id": CELL,
            "opcua_endpoint": endpoint(opcua_port),
            **broker.cell_login,
            "mqtt_commands": True,
        }
        async with (
            open_rig(data, **overrides) as rig,
            aiomqtt.Client(
                "127.0.0.1",
                broker.port,
                protocol=aiomqtt.ProtocolVersion.V5,
                **login_of("operator"),
            ) as mqtt_client,
        ):
            mqtt = MqttRequester(mqtt_client)
            await mqtt.subscribe()
            await _until_mqtt_linked(rig)
            yield rig, mqtt


async def _opc_start(opc: Client, value: Any) -> ua.CallMethodResult:
    """Start with `value` as WorkpieceId, typed as a client would send it: a string, or a
    Double where a number was put in the string's place."""
    ns = await opc.get_namespace_index(NAMESPACE_URI)
    request = ua.CallMethodRequest()
    request.ObjectId = ua.NodeId.from_string(f"ns={ns};s={CELL}")
    request.MethodId = ua.NodeId.from_string(f"ns={ns};s={CELL}.Start")
    kind = ua.VariantType.Double if isinstance(value, float) else ua.VariantType.String
    request.InputArguments = [ua.Variant(value, kind)]
    (result,) = await opc.uaclient.call([request])
    return result


def _size(directory: Path) -> int:
    return sum(f.stat().st_size for f in directory.rglob("*") if f.is_file())


async def _refusals(rig: Rig, action: str) -> list[tuple[str, str]]:
    audit = (await rig.api.get("/audit", params={"limit": 1000})).json()["audit"]
    # Identical refusals are folded into one row with their count (docs/security.md).
    rows = [r for r in audit if r["action"] == action]
    return sorted((r["outcome"], r["detail"]) for r in rows for _ in range(r["count"]))


async def test_bad_inputs_are_refused_alike_over_http_mqtt_and_opcua(tmp_path: Path) -> None:
    port = free_port()
    data = tmp_path / "data"
    async with cell_on_three_doors(tmp_path / "broker", data, port) as (rig, mqtt):
        operator = await make_token(rig, "operator")
        maintenance = await make_token(rig, "maintenance")
        opc = Client(endpoint(port), timeout=WAIT_S)
        opc.set_user("plc")
        opc.set_password(operator)
        path_before, pose_before = len(rig.robot.path_snapshot()), rig.robot.position
        size_before = _size(data)
        async with opc:
            for name, value in BAD_IDS.items():
                body = {"contour_matching": False, "workpiece_id": value}
                http = await rig.api.post(
                    "/start", content=_json(body), headers={"content-type": "application/json"}
                )
                assert http.status_code == 422, (name, http.text)
                detail = http.json()["detail"]
                assert [e["field"] for e in http.json()["errors"]] == ["workpiece_id"], name

                over_mqtt = await mqtt.command("start", operator, body)
                assert over_mqtt["status"] == 422, (name, over_mqtt)
                assert over_mqtt["detail"] == detail, name
                assert over_mqtt["errors"] == http.json()["errors"], name

                over_opc = await _opc_start(opc, value)
                assert over_opc.StatusCode.value == ua.StatusCodes.BadInvalidArgument, (
                    name,
                    over_opc,
                )
                assert over_opc.OutputArguments[0].Value is False
                assert over_opc.OutputArguments[2].Value == detail, name
                assert "workpiece_id" in detail

            # 5 MB: too large to read over HTTP (413) and OPC UA (BadRequestTooLarge).
            huge = {"contour_matching": False, "workpiece_id": FIVE_MB}
            http = await rig.api.post("/start", json=huge)
            assert http.status_code == 413, http.text
            with pytest.raises(ua.UaStatusCodeError) as too_large:
                await _opc_start(opc, FIVE_MB)
            assert too_large.value.code == ua.StatusCodes.BadRequestTooLarge
            # MQTT reads it (the broker's limit is its cap) and the model refuses it.
            over_mqtt = await mqtt.command("start", operator, huge)
            assert over_mqtt["status"] == 422, str(over_mqtt)[:500]
            assert [e["field"] for e in over_mqtt["errors"]] == ["workpiece_id"]
            huge_detail = over_mqtt["detail"]

            # The session is still usable after the refusals: a good id is accepted
            # as over HTTP (here the state's own answer to a resume).
            resumed = await _opc_call(opc, "Resume")
            assert resumed.StatusCode.value == ua.StatusCodes.BadInvalidState

        # A number's NaN and infinity, where a command takes a number (jog: HTTP, MQTT).
        for value in (math.nan, math.inf):
            body = {"axis": "x", "distance_mm": value}
            http = await rig.api.post(
                "/jog", content=_json(body), headers={"content-type": "application/json"}
            )
            assert http.status_code == 422, http.text
            assert [e["field"] for e in http.json()["errors"]] == ["distance_mm"]
            over_mqtt = await mqtt.command("jog", maintenance, body)
            assert over_mqtt["status"] == 422, over_mqtt
            assert over_mqtt["detail"] == http.json()["detail"]

        # Nothing reached the worker: the state, the robot, the journal's size.
        assert (await rig.state())["state"] == "IDLE"
        assert len(rig.robot.path_snapshot()) == path_before
        assert rig.robot.position == pose_before
        grown = _size(data) - size_before
        assert grown < 512 * 1024, f"the data directory grew by {grown} bytes"

        # The audit trail says the same of each refusal, whichever door it came by.
        http_rows = await _refusals(rig, START)
        mqtt_rows = await _refusals(rig, MQTT_START)
        opc_rows = await _refusals(rig, OPC_START)
        details = sorted(d for o, d in http_rows if o == "refused (422)")
        assert len(details) == len(BAD_IDS), http_rows
        assert [d for _, d in opc_rows] == details, (opc_rows, details)
        assert {o for o, _ in opc_rows} == {"refused (BadInvalidArgument)"}
        assert mqtt_rows == sorted(
            [("refused (422)", d) for d in details] + [("refused (422)", huge_detail)]
        ), mqtt_rows
        # (HTTP's 413 for a declared Content-Length is answered by the outermost
        # middleware, outside the audit observer: no row; OPC UA's is audited.)
        calls = await _refusals(rig, "OPC UA Call")
        assert [o for o, _ in calls] == ["refused (BadRequestTooLarge)"], calls
        everything = json.dumps((await rig.api.get("/audit", params={"limit": 1000})).json())
        for value in ("../../etc/passwd", "\u202e", "aaaaaaaaaaaaaaaaaaaaaaaaaaaa"):
            assert value not in everything  # a refusal names the field, not the value


async def _opc_call(opc: Client, method: str) -> ua.CallMethodResult:
    ns = await opc.get_namespace_index(NAMESPACE_URI)
    request = ua.CallMethodRequest()
    request.ObjectId = ua.NodeId.from_string(f"ns={ns};s={CELL}")
    request.MethodId = ua.NodeId.from_string(f"ns={ns};s={CELL}.{method}")
    (result,) = await opc.uaclient.call([request])
    return result


async def _until_mqtt_linked(rig: Rig) -> None:
    """Until the cell's MQTT link is up (its /health says so)."""
    async with asyncio.timeout(WAIT_S):
        while not (await rig.api.get("/health")).json().get("mqtt", {}).get("connected"):
            await asyncio.sleep(0.05)


async def test_a_5_mb_opcua_argument_is_refused_before_it_is_read(tmp_path: Path) -> None:
    """A 5 MB WorkpieceId, decoded and journaled, would take a second and leave a 15 MB
    journal plus a 15 MB WAL: the call is refused by its size before asyncua decodes it."""
    port = free_port()
    data = tmp_path / "data"
    async with open_rig(data, cell_id=CELL, opcua_endpoint=endpoint(port)) as rig:
        operator = await make_token(rig, "operator")
        opc = Client(endpoint(port), timeout=WAIT_S)
        opc.set_user("plc")
        opc.set_password(operator)
        size_before = _size(data)
        async with opc:
            with pytest.raises(ua.UaStatusCodeError) as too_large:
                await _opc_start(opc, FIVE_MB)
            assert too_large.value.code == ua.StatusCodes.BadRequestTooLarge
            # The session goes on: the next call is answered by the cell.
            resumed = await _opc_call(opc, "Resume")
            assert resumed.StatusCode.value == ua.StatusCodes.BadInvalidState
        assert (await rig.state())["state"] == "IDLE"
        grown = _size(data) - size_before
        assert grown < 512 * 1024, f"the data directory grew by {grown} bytes"
        (row,) = [
            r
            for r in (await rig.api.get("/audit", params={"limit": 100})).json()["audit"]
            if r["action"] == "OPC UA Call"
        ]
        assert row["outcome"] == "refused (BadRequestTooLarge)"
        assert row["principal"].startswith("plc-operator (operator")
