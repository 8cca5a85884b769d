"""The stop through every door: an e-stop sent behind a flood of that door's own commands
is decided ahead of the flood's commands that were sent before it.

Each door has a queue of its own in front of the worker's: MQTT's is the client's
incoming queue (the broker delivers in order, the link reads one message at a
time), OPC UA's the session's calls, served in order. The stop must not wait in
it. Seen in the journal: the EMERGENCY_STOP's row comes before the rows of flood
commands the client sent before the stop. Nothing here is timed; the order of
the journal's rows is the measure.
"""

from __future__ import annotations

import asyncio
import json
import sqlite3
import threading
from pathlib import Path
from typing import Any

import httpx
import paho.mqtt.client as paho
from asyncua import Client, ua
from paho.mqtt.enums import CallbackAPIVersion
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from clients.client.mqtt_signing import sign_command
from server.commands.catalogue import ADMITTED
from server.line.broker import DEMO_PASSWORDS
from server.opcua.address_space import NAMESPACE_URI
from tests.mosquitto import WAIT_S, mosquitto
from tests.rig import Rig, open_rig
from tests.serving import free_port

CELL = "cell-7"
BASE = f"glue/{CELL}"
FLOOD = 600  # under mosquitto's default max_queued_messages (1000) for one client
HTTP_BURST = 40  # requests at once, each on a connection of its own


def _publish_flood_then_stop(port: int, token: str, command: str = "pause") -> None:
    """FLOOD signed `command`s, each asking for its answer, then one `estop`, on one
    connection, in this order (MQTT keeps a client's order), each acknowledged (QoS 1);
    returns once every one of them is answered."""
    client = paho.Client(CallbackAPIVersion.VERSION2, protocol=paho.MQTTv5)
    client.username_pw_set("operator", DEMO_PASSWORDS["operator"])
    client.max_inflight_messages_set(0)  # no limit: the whole flood is on its way at once
    client.max_queued_messages_set(0)
    answered = threading.Semaphore(0)
    client.on_message = lambda *_: answered.release()
    client.connect("127.0.0.1", port)
    client.loop_start()
    try:
        reply_to = f"{BASE}/response/flood"
        client.subscribe(reply_to, qos=1)  # before the commands: the broker keeps order
        properties = Properties(PacketTypes.PUBLISH)
        properties.ResponseTopic = reply_to
        infos = []
        for _ in range(FLOOD):
            topic = f"{BASE}/command/{command}"
            payload = json.dumps(sign_command(token, topic, None)).encode()
            infos.append(client.publish(topic, payload, qos=1, properties=properties))
        topic = f"{BASE}/command/estop"
        payload = json.dumps(sign_command(token, topic, {"reason": "behind the flood"})).encode()
        infos.append(client.publish(topic, payload, qos=1, properties=properties))
        for info in infos:
            info.wait_for_publish(WAIT_S)
        for _ in infos:  # each read and answered by the cell: none still on its way
            assert answered.acquire(timeout=WAIT_S), "a command was never answered"
    finally:
        client.loop_stop()
        client.disconnect()


class CommandsInside:
    """Counts, through `rig.cell.command`, the commands (not stops) from a source starting
    with `source` that are in the cell at once; `most`, the most at any moment."""

    def __init__(self, rig: Rig, source: str) -> None:
        self.inside = self.most = 0
        command = rig.cell.command

        async def counted(what: Any, **kwargs: Any) -> Any:
            if not kwargs.get("source", "").startswith(source) or what.value == "estop":
                return await command(what, **kwargs)
            self.inside += 1
            self.most = max(self.most, self.inside)
            try:
                return await command(what, **kwargs)
            finally:
                self.inside -= 1

        rig.cell.command = counted  # type: ignore[method-assign]


async def _link_up(rig: Rig) -> None:
    async with asyncio.timeout(WAIT_S):
        while not (await rig.api.get("/health")).json()["mqtt"]["connected"]:
            await asyncio.sleep(0.05)


def _events(data: Path) -> list[tuple[str, str]]:
    """Every event the worker decided, in the order it decided them: (type, source)."""
    with sqlite3.connect(data / "journal.db") as db:
        return list(db.execute("SELECT type, source FROM events ORDER BY rowid"))


async def test_an_mqtt_stop_behind_a_flood_is_decided_before_the_flood_sent_ahead_of_it(
    tmp_path: Path,
) -> None:
    with mosquitto(tmp_path / "broker") as broker:
        async with open_rig(
            tmp_path / "data", **broker.cell_login, cell_id=CELL, mqtt_commands=True
        ) as rig:
            await _link_up(rig)
            made = await rig.api.post("/tokens", json={"name": "mes", "role": "operator"})
            token = made.json()["token"]
            done = threading.Event()

            def publish() -> None:
                try:
                    _publish_flood_then_stop(broker.port, token)
                finally:
                    done.set()

            thread = threading.Thread(target=publish, daemon=True)
            thread.start()
            await rig.wait_state("ERROR")
            # Every command answered: each pause refused by the worker (IDLE, then ERROR:
            # 409) or at the door (503, too many at once).
            async with asyncio.timeout(WAIT_S):
                while not done.is_set():
                    await asyncio.sleep(0.05)
            assert rig.cell.journal is not None
            await rig.cell.journal.caught_up()
            mqtt = [kind for kind, source in _events(tmp_path / "data") if source == "mqtt:mes"]
            assert "EMERGENCY_STOP" in mqtt, mqtt
            stop_at = mqtt.index("EMERGENCY_STOP")
            before, after = mqtt[:stop_at], mqtt[stop_at + 1 :]
            # Read after the stop, a pause signed before it is refused at the door
            # (server/mqtt/commands.py), so it never reaches the worker.
            with sqlite3.connect(tmp_path / "data" / "journal.db") as db:
                (refused,) = db.execute(
                    "SELECT COUNT(*) FROM audit WHERE detail LIKE 'sent before an emergency%'"
                ).fetchone()
            print(
                f"pauses decided before the stop: {len(before)}, after it: {len(after)}, "
                f"refused at the door as sent before it: {refused}"
            )
            # Every pause was sent before the stop; the stop went ahead of most of them.
            assert len(after) + refused > len(before), (len(before), len(after), refused)


BURST = 450  # OPC UA calls on one session, sent before the stop (a session may have 500 waiting)


async def _burst_then_stop(
    rig: Rig, port: int, method: str = "Pause", role: str = "operator"
) -> list[Any]:
    """BURST `method` calls (Pause: refused in IDLE), then an EmergencyStop, on one
    session, every request on its way before the first is answered; the answers, in the
    same order."""
    made = await rig.api.post("/tokens", json={"name": "plc", "role": role})
    # The client probes the server every watchdog_intervall and gives up on a slow
    # answer: on a busy shared machine that is not the connection lost.
    opc = Client(f"opc.tcp://127.0.0.1:{port}", timeout=WAIT_S, watchdog_intervall=WAIT_S)
    # asyncua's client sends 100 requests at a time by default, the rest after answers:
    # the whole burst and the stop on their way at once instead.
    opc.uaclient.set_max_concurrent_requests(BURST + 1)
    opc.set_user("plc")
    opc.set_password(made.json()["token"])
    async with opc:
        ns = await opc.get_namespace_index(NAMESPACE_URI)

        def request(method: str) -> ua.CallMethodRequest:
            call = ua.CallMethodRequest()
            call.ObjectId = ua.NodeId.from_string(f"ns={ns};s={CELL}")
            call.MethodId = ua.NodeId.from_string(f"ns={ns};s={CELL}.{method}")
            call.InputArguments = []
            return call

        calls = [asyncio.ensure_future(opc.uaclient.call([request(method)])) for _ in range(BURST)]
        calls.append(asyncio.ensure_future(opc.uaclient.call([request("EmergencyStop")])))
        return list(await asyncio.gather(*calls))


async def test_an_opcua_stop_behind_a_burst_of_calls_is_decided_before_the_burst(
    tmp_path: Path,
) -> None:
    port = free_port()
    overrides = {"cell_id": CELL, "opcua_endpoint": f"opc.tcp://127.0.0.1:{port}"}
    async with open_rig(tmp_path / "data", **overrides) as rig:
        answers = await _burst_then_stop(rig, port)
        assert answers[-1][0].StatusCode.is_good(), answers[-1]
        await rig.wait_state("ERROR")
        assert rig.cell.journal is not None
        await rig.cell.journal.caught_up()
        ours = [kind for kind, source in _events(tmp_path / "data") if source.startswith("opcua:")]
        stop_at = ours.index("EMERGENCY_STOP")
        before, after = ours[:stop_at], ours[stop_at + 1 :]
        print(f"pauses decided before the stop: {len(before)}, after it: {len(after)}")
        assert len(before) + len(after) == BURST  # every Pause reached the worker
        # The session's requests are read in order (its channel is decrypted in order), so
        # the stop comes after the calls ahead of it are read; but not after they are
        # decided and answered: it overtakes those still waiting for the worker.
        assert after, "the stop waited for every call sent before it to be decided"


async def test_an_opcua_burst_is_served_a_few_calls_at_a_time_and_a_stop_ahead_of_the_rest(
    tmp_path: Path,
) -> None:
    """The OPC UA lane admits at most ADMITTED calls into the cell at once; the rest wait
    in its line without a task, and a stop read behind them is made before they are."""
    port = free_port()
    overrides = {"cell_id": CELL, "opcua_endpoint": f"opc.tcp://127.0.0.1:{port}"}
    async with open_rig(tmp_path / "data", **overrides) as rig:
        command = rig.cell.command
        inside: list[str] = []  # the OPC UA commands in the cell now
        most = 0  # the most non-stop commands that were in the cell at once
        entered: list[str] = []  # every command, in the order it entered the cell

        async def counted(what: Any, **kwargs: Any) -> Any:
            nonlocal most
            if not kwargs.get("source", "").startswith("opcua:"):
                return await command(what, **kwargs)
            entered.append(what.value)
            inside.append(what.value)
            most = max(most, sum(1 for name in inside if name != "estop"))
            try:
                return await command(what, **kwargs)
            finally:
                inside.remove(what.value)

        rig.cell.command = counted  # type: ignore[method-assign]
        answers = await _burst_then_stop(rig, port)
        assert answers[-1][0].StatusCode.is_good(), answers[-1]
        assert all(answer[0].StatusCode.is_bad() for answer in answers[:-1])  # refused: 409
        assert len(entered) == BURST + 1  # every call reached the cell: none lost
        print(
            f"at most {most} calls in the cell at once; the stop entered {entered.index('estop')}th"
        )
        assert 0 < most <= ADMITTED
        # The stop is read right behind the burst; with a few calls served at a time most
        # of the burst is still in the line then, and the stop goes in ahead of it.
        assert entered.index("estop") < BURST // 2


async def test_an_mqtt_flood_is_served_a_few_commands_at_a_time(tmp_path: Path) -> None:
    """The MQTT link serves at most ADMITTED commands at once (server/mqtt/link.py); the
    rest wait in the client's incoming queue, and every one is still answered."""
    with mosquitto(tmp_path / "broker") as broker:
        async with open_rig(
            tmp_path / "data", **broker.cell_login, cell_id=CELL, mqtt_commands=True
        ) as rig:
            await _link_up(rig)
            counted = CommandsInside(rig, "mqtt:")
            made = await rig.api.post("/tokens", json={"name": "mes", "role": "operator"})
            await asyncio.to_thread(_publish_flood_then_stop, broker.port, made.json()["token"])
            await rig.wait_state("ERROR")
        print(f"at most {counted.most} MQTT commands in the cell at once")
        assert 0 < counted.most <= ADMITTED


async def test_an_http_burst_is_served_a_few_commands_at_a_time(tmp_path: Path) -> None:
    """The HTTP door serves at most ADMITTED commands at once (server/api/door.py); the
    others wait before their bodies are read, and every one is still answered."""
    async with open_rig(tmp_path / "data") as rig:
        counted = CommandsInside(rig, "api:")
        pool = httpx.Limits(max_connections=HTTP_BURST)
        async with httpx.AsyncClient(
            base_url=rig.api.base_url, headers=rig.api.headers, limits=pool, timeout=WAIT_S
        ) as burst:
            answers = await asyncio.gather(*(burst.post("/pause") for _ in range(HTTP_BURST)))
        assert [answer.status_code for answer in answers] == [409] * HTTP_BURST  # IDLE
    print(f"at most {counted.most} HTTP commands in the cell at once")
    assert 0 < counted.most <= ADMITTED


async def test_a_reset_sent_before_a_stop_never_clears_that_stop(tmp_path: Path) -> None:
    """Resets read before a stop and still waiting when it is made are refused, so the
    stop's ERROR stays until a reset sent after it (server/core/machine/decide.py, "asked
    before a stop"): decided after the stop, one of them would take the cell to IDLE."""
    port = free_port()
    overrides = {"cell_id": CELL, "opcua_endpoint": f"opc.tcp://127.0.0.1:{port}"}
    async with open_rig(tmp_path / "data", **overrides) as rig:
        assert (await rig.api.post("/estop", json={"reason": "a first stop"})).status_code == 202
        await rig.wait_state("ERROR")  # where a reset is allowed
        answers = await _burst_then_stop(rig, port, "Reset", "maintenance")
        assert answers[-1][0].StatusCode.is_good(), answers[-1]
        state = (await rig.api.get("/state")).json()
        assert state["state"] == "ERROR", state
        assert rig.cell.journal is not None
        await rig.cell.journal.caught_up()
        with sqlite3.connect(tmp_path / "data" / "journal.db") as db:
            refused = db.execute(
                "SELECT COUNT(*) FROM events WHERE type = 'RESET_REQUESTED' "
                "AND message LIKE 'sent before an emergency stop%'"
            ).fetchone()[0]
        print(f"resets refused as sent before the stop: {refused}")
        assert refused > 0


async def test_an_mqtt_reset_signed_before_a_stop_never_clears_it(tmp_path: Path) -> None:
    """The stop lane's connection brings the stop ahead of the resets its sender published
    before it; read after it, each of them is refused (server/mqtt/commands.py), and the
    stop's ERROR stays."""
    with mosquitto(tmp_path / "broker") as broker:
        async with open_rig(
            tmp_path / "data", **broker.cell_login, cell_id=CELL, mqtt_commands=True
        ) as rig:
            await _link_up(rig)
            assert (
                await rig.api.post("/estop", json={"reason": "a first stop"})
            ).status_code == 202
            await rig.wait_state("ERROR")  # where a reset is allowed
            made = await rig.api.post("/tokens", json={"name": "mes", "role": "maintenance"})
            await asyncio.to_thread(
                _publish_flood_then_stop, broker.port, made.json()["token"], "reset"
            )
            state = (await rig.api.get("/state")).json()
            assert state["state"] == "ERROR", state
            assert rig.cell.journal is not None
            await rig.cell.journal.caught_up()
            with sqlite3.connect(tmp_path / "data" / "journal.db") as db:
                refused = db.execute(
                    "SELECT COUNT(*) FROM audit WHERE detail LIKE 'sent before an emergency%'"
                ).fetchone()[0]
            print(f"resets refused as signed before the stop: {refused}")
            assert refused > 0
