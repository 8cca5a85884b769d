"""Signed MQTT commands against Debian's mosquitto with the shipped ACL and a real cell.

A command captured on the broker must carry no secret (a token in clear would also
work as an HTTP bearer token) and must not start a new run when published again. A
command is signed (clients/client/mqtt_signing.py): the capture holds no secret, and
the same message again, too old or from the future is refused on the response topic
and in the audit trail, and moves nothing. The broker refuses anonymous clients, and
the line view can neither read commands nor send them. gluectl --mqtt and the Python
client sign for the script.
"""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import time
import uuid
from pathlib import Path

import aiomqtt
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from clients.client import Refused
from clients.client.mqtt_commands import AsyncMqttCommands, MqttTarget
from clients.client.mqtt_signing import sign_command
from server.line.broker import DEMO_PASSWORDS
from tests.mosquitto import WAIT_S, Mosquitto, login_of, mosquitto
from tests.processes import ROOT, environment
from tests.rig import SPRAY_DEMO, open_rig

CELL = "cell-5"
BASE = f"glue/{CELL}"


class Requester:
    """An MQTT v5 client that publishes raw payloads and reads each answer."""

    def __init__(self, client: aiomqtt.Client) -> None:
        self.client = client
        self.reply_to = f"{BASE}/response/{uuid.uuid4().hex}"

    async def ask(self, name: str, payload: bytes) -> dict:
        correlation = uuid.uuid4().bytes
        properties = Properties(PacketTypes.PUBLISH)
        properties.ResponseTopic = self.reply_to
        properties.CorrelationData = correlation
        await self.client.publish(f"{BASE}/command/{name}", payload, qos=1, properties=properties)
        async with asyncio.timeout(WAIT_S):
            async for answer in self.client.messages:
                if str(answer.topic) != self.reply_to:
                    continue
                assert answer.properties.CorrelationData == correlation  # type: ignore[union-attr]
                return json.loads(bytes(answer.payload))
        raise AssertionError("no answer")


async def _sniffed(sniffer: aiomqtt.Client, topic: str) -> bytes:
    async with asyncio.timeout(WAIT_S):
        async for message in sniffer.messages:
            if str(message.topic) == topic:
                return bytes(message.payload)
    raise AssertionError("nothing captured")


async def _link_up(rig) -> None:
    async with asyncio.timeout(WAIT_S):
        while not (await rig.api.get("/health")).json()["mqtt"]["connected"]:
            await asyncio.sleep(0.05)


async def _runs(rig) -> int:
    params = {"new_state": "EXECUTING_TRAJECTORY"}
    return int((await rig.api.get("/history", params=params)).json()["total"])


async def test_a_captured_command_has_no_secret_and_is_refused_when_replayed(
    tmp_path: Path,
) -> None:
    with mosquitto(tmp_path / "broker") as broker:
        async with (
            open_rig(
                tmp_path / "data", **broker.cell_login, cell_id=CELL, mqtt_commands=True
            ) as rig,
            # The only user the ACL lets read commands: what a sniffer could at worst see.
            aiomqtt.Client("127.0.0.1", broker.port, **login_of("cell")) as sniffer,
            aiomqtt.Client(
                "127.0.0.1",
                broker.port,
                protocol=aiomqtt.ProtocolVersion.V5,
                **login_of("operator"),
            ) as client,
        ):
            await _link_up(rig)
            made = await rig.api.post("/tokens", json={"name": "mes", "role": "operator"})
            token = made.json()["token"]
            await sniffer.subscribe(f"{BASE}/command/#", qos=1)
            requester = Requester(client)
            await client.subscribe(requester.reply_to, qos=1)

            topic = f"{BASE}/command/start"
            sent = json.dumps(sign_command(token, topic, SPRAY_DEMO)).encode()
            answer = await requester.ask("start", sent)
            assert answer["status"] == 202 and answer["run_id"], answer
            captured = await _sniffed(sniffer, topic)
            secret = token.split("_", 2)[2]
            assert secret not in captured.decode() and token not in captured.decode()
            await rig.wait_state("IDLE")
            runs = await _runs(rig)
            assert runs == 1

            # The capture, published again: refused, nothing started.
            answer = await requester.ask("start", captured)
            assert answer["status"] == 401 and "replayed" in answer["detail"], answer
            # Signed long ago (a capture kept for later), or ahead of the cell's clock.
            now_ms = int(time.time() * 1000)
            stale = sign_command(token, topic, SPRAY_DEMO, now_ms=now_ms - 31_000)
            answer = await requester.ask("start", json.dumps(stale).encode())
            assert answer["status"] == 401 and "stale" in answer["detail"], answer
            ahead = sign_command(token, topic, SPRAY_DEMO, now_ms=now_ms + 60_000)
            answer = await requester.ask("start", json.dumps(ahead).encode())
            assert answer["status"] == 401 and "future" in answer["detail"], answer
            # The body changed under the signature; the old form with the token in clear.
            forged = {**json.loads(captured), "body": {"workpiece_id": "other"}}
            answer = await requester.ask("start", json.dumps(forged).encode())
            assert answer["status"] == 401 and "signature" in answer["detail"], answer
            old = json.dumps({"token": token, "body": SPRAY_DEMO}).encode()
            answer = await requester.ask("start", old)
            assert answer["status"] == 401 and "sign the command" in answer["detail"], answer
            assert token not in json.dumps(answer)

            assert (await rig.state())["state"] == "IDLE"
            assert await _runs(rig) == runs  # no refusal moved anything
            audit = (await rig.api.get("/audit", params={"limit": 1000})).json()["audit"]
            refused = [
                a for a in audit if a["action"] == f"MQTT {topic}" and a["outcome"] != "accepted"
            ]
            details = " | ".join(a["detail"] for a in refused)
            for word in ("replayed", "stale", "future", "signature", "sign the command"):
                assert word in details, details
            assert secret not in json.dumps(audit)


async def test_the_broker_refuses_anonymous_and_the_line_view_cannot_touch_commands(
    tmp_path: Path,
) -> None:
    with mosquitto(tmp_path / "broker") as broker:
        try:
            async with aiomqtt.Client("127.0.0.1", broker.port):
                raise AssertionError("an anonymous client was let in")
        except aiomqtt.MqttError as refused:
            assert "authori" in str(refused).lower(), refused
        async with (
            aiomqtt.Client("127.0.0.1", broker.port, **login_of("cell")) as cell,
            aiomqtt.Client("127.0.0.1", broker.port, **login_of("line-view")) as view,
            aiomqtt.Client("127.0.0.1", broker.port, **login_of("operator")) as operator,
        ):
            await cell.subscribe(f"{BASE}/command/#", qos=1)
            await view.subscribe("#", qos=1)
            await view.publish(f"{BASE}/command/start", b"from the line view", qos=1)
            await operator.publish(f"{BASE}/command/start", b"from an operator", qos=1)
            await cell.publish(f"{BASE}/state", b"IDLE", qos=1)
            # The cell hears the operator's command and only it (the broker keeps order).
            assert await _sniffed(cell, f"{BASE}/command/start") == b"from an operator"
            # The line view hears the state, and never a command.
            assert await _sniffed(view, f"{BASE}/state") == b"IDLE"
            await cell.publish(f"{BASE}/status", b"online", qos=1)
            assert await _sniffed(view, f"{BASE}/status") == b"online"  # after the commands


def _gluectl(
    broker: Mosquitto, token: str, *args: str, password_file: Path
) -> subprocess.CompletedProcess[str]:
    argv = [sys.executable, "-m", "clients.gluectl", "--mqtt", broker.url, "--cell-id", CELL]
    argv += ["--mqtt-user", "operator", "--mqtt-password-file", str(password_file)]
    return subprocess.run(
        [*argv, "--json", *args],
        capture_output=True,
        text=True,
        env=environment({"GLUE_CELL_TOKEN": token}),
        cwd=ROOT,
        timeout=120,
    )


async def test_gluectl_and_the_client_send_signed_commands(tmp_path: Path) -> None:
    password_file = tmp_path / "operator.password"
    password_file.write_text(DEMO_PASSWORDS["operator"] + "\n")
    with mosquitto(tmp_path / "broker") as broker:
        async with open_rig(
            tmp_path / "data", **broker.cell_login, cell_id=CELL, mqtt_commands=True
        ) as rig:
            await _link_up(rig)
            tokens = {}
            for role in ("operator", "maintenance"):
                made = await rig.api.post("/tokens", json={"name": f"script-{role}", "role": role})
                tokens[role] = made.json()["token"]

            def gluectl(role: str, *args: str) -> subprocess.CompletedProcess[str]:
                return _gluectl(broker, tokens[role], *args, password_file=password_file)

            started = await asyncio.to_thread(
                gluectl, "operator", "start", "--no-contour-matching", "--workpiece", "demo"
            )
            assert started.returncode == 0, started.stderr
            answer = json.loads(started.stdout)
            assert answer["accepted"] is True and answer["status_code"] == 202
            assert answer["state"] == "EXECUTING_TRAJECTORY" and answer["run_id"]
            paused = await asyncio.to_thread(gluectl, "operator", "pause")
            assert paused.returncode == 0, paused.stderr
            await rig.wait_state("PAUSED")
            for step in ("resume", "cancel"):
                done = await asyncio.to_thread(gluectl, "operator", step)
                assert done.returncode == 0, done.stderr
            await rig.wait_state("IDLE")
            # As over HTTP: a reset needs maintenance (exit 4), home is refused nowhere near.
            refused = await asyncio.to_thread(gluectl, "operator", "home")
            assert refused.returncode == 4 and "maintenance" in refused.stderr, refused
            stopped = await asyncio.to_thread(gluectl, "operator", "estop", "--reason", "drill")
            assert stopped.returncode == 0, stopped.stderr
            await rig.wait_state("ERROR")
            again = await asyncio.to_thread(gluectl, "operator", "resume")
            assert again.returncode == 3 and json.loads(again.stdout)["error"] == "Refused"
            reset = await asyncio.to_thread(gluectl, "maintenance", "reset")
            assert reset.returncode == 0, reset.stderr
            await rig.wait_state("IDLE")
            home = await asyncio.to_thread(gluectl, "maintenance", "home")
            assert home.returncode == 0, home.stderr
            # Only commands go over MQTT; a query says where to ask instead.
            query = await asyncio.to_thread(gluectl, "operator", "state")
            assert query.returncode == 2 and "only commands" in query.stdout + query.stderr
            # No answer from a cell that is not there: unreachable (5), in bounded time.
            absent = await asyncio.to_thread(
                gluectl, "operator", "--http-timeout", "1", "--cell-id", "cell-404", "pause"
            )
            assert absent.returncode == 5 and "cell-404" in absent.stderr, absent

            # The Python client, asyncio: the same answers, the same exceptions.
            target = MqttTarget(
                broker.url, CELL, username="operator", password=DEMO_PASSWORDS["operator"]
            )
            assert DEMO_PASSWORDS["operator"] not in repr(target)
            await rig.wait_state("IDLE")
            async with AsyncMqttCommands(target, tokens["operator"]) as commands:
                result = await commands.start("demo", contour_matching=False)
                assert result.accepted and result.run_id
                try:
                    await commands.command("resume")
                    raise AssertionError("resume while spraying was accepted")
                except Refused as refusal:
                    assert refusal.result.status_code == 409
                assert (await commands.command("cancel")).accepted
            await rig.wait_state("IDLE")
