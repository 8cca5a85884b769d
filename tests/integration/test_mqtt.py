"""The cell on a plant's MQTT broker: Debian's mosquitto as a process, the cell
publishing to it through its production link, and subscribers and requesters
that are plain MQTT clients (aiomqtt, on paho).

What a plant would notice: a late subscriber finds the state; every transition
of a run arrives in order; a killed server shows `offline` (its last will) and a
stopped one says so itself; what happened while the broker was away arrives
when it is back, the newest first kept and the rest counted; signed commands over
MQTT are refused without a valid token or the role and answered on the v5 response
topic with the correlation data, through the same path as HTTP.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import subprocess
import uuid
from collections.abc import AsyncIterator, Callable
from pathlib import Path

import aiomqtt
import httpx
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from clients.client.mqtt_signing import sign_command
from server.core.operations.safe_position import RETRACT_STEP
from server.mqtt.link import BUS_TYPES
from tests.mosquitto import WAIT_S, login_of, mosquitto, subscriber
from tests.processes import server_process
from tests.rig import SPRAY_DEMO, open_rig, run
from tests.serving import admin_headers, free_port

CELL = "cell-7"
BASE = f"glue/{CELL}"


async def test_a_run_in_order_and_the_state_for_a_late_subscriber(tmp_path: Path) -> None:
    with mosquitto(tmp_path / "broker") as broker:
        async with (
            # Every waypoint (plant_progress_interval 0), to check them all in order.
            open_rig(
                tmp_path / "data", **broker.cell_login, cell_id=CELL, plant_progress_interval=0
            ) as rig,
            subscriber(broker.port, f"{BASE}/#") as early,
        ):
            truth = rig.cell.bus.subscribe(4096, types=["state_changed"])
            final = await run(rig, "start", SPRAY_DEMO)
            assert final["state"] == "IDLE"
            transitions = []
            while truth.pending:
                transitions.append((await truth.get()).data)
            assert [t["new_state"] for t in transitions] == ["EXECUTING_TRAJECTORY", "IDLE"]

            # The start-up's INITIALIZING -> IDLE may reach the broker after this subscriber
            # came, when the link connected after it (buffered, then sent): not the run's.
            def run_events() -> list[dict]:
                return [e for e in early.on(f"{BASE}/event") if e["from"] != "INITIALIZING"]

            events = await early.wait(lambda: (e := run_events()) and len(e) >= 2 and e)
            # The WebSocket's names (old_state, new_state, timestamp), the old ones beside them.
            assert [(e["old_state"], e["new_state"], e["event_id"]) for e in events] == [
                (t["old_state"], t["new_state"], t["event_id"]) for t in transitions
            ]
            assert [(e["timestamp"], e["time_in_old_state"]) for e in events] == [
                (t["timestamp"], t["time_in_old_state"]) for t in transitions
            ]
            assert all((e["from"], e["to"]) == (e["old_state"], e["new_state"]) for e in events)
            assert [e["seq"] for e in events] == sorted(e["seq"] for e in events)
            assert all(e["cell_id"] == CELL for e in events)
            run_id = events[0]["event_id"]
            states = early.on(f"{BASE}/state")
            running = [s for s in states if s["state"] == "EXECUTING_TRAJECTORY"]
            assert running and running[0]["run_id"] == run_id
            assert running[0]["workpiece_id"] == "demo"
            progress = early.on(f"{BASE}/progress")
            assert progress and {p["run_id"] for p in progress} == {run_id}
            assert {p["state"] for p in progress} == {"EXECUTING_TRAJECTORY"}  # as on /ws
            # Each waypoint once, in order (plant_progress_interval 0: none thinned).
            # each waypoint's own message (the retract, the run's last step, repeats the last)
            reached = [p["waypoint"] for p in progress if p.get("step") != RETRACT_STEP]
            assert reached == list(range(1, progress[-1]["total"] + 1))
            assert progress[-1]["fraction"] == 1.0

            # A subscriber that comes later is told the present by the broker alone.
            async with subscriber(broker.port, f"{BASE}/#") as late:
                state = await late.wait(lambda: late.on(f"{BASE}/state"))
                assert state[-1] == {
                    **state[-1],
                    "cell_id": CELL,
                    "state": "IDLE",
                    "since": final["since"],
                    "stop_reason": None,
                    "run_id": None,
                }
                status = await late.wait(lambda: late.on(f"{BASE}/status"))
                assert [(s["cell_id"], s["status"]) for s in status] == [(CELL, "online")]
                assert isinstance(status[0]["time"], float)  # when it came online
                health = await late.wait(lambda: late.on(f"{BASE}/health"))
                assert health[-1]["mqtt"]["connected"] is True
                assert health[-1]["cell_id"] == CELL  # every topic names its cell; not health
                kpis = await late.wait(lambda: late.on(f"{BASE}/kpis"))
                assert kpis[-1]["cell_id"] == CELL and "oee" in json.dumps(kpis[-1])
                assert not late.on(f"{BASE}/event")  # not retained: history is not replayed

            over_http = (await rig.api.get("/health")).json()["mqtt"]
            assert over_http["connected"] is True and over_http["dropped"] == 0
            settings = (await rig.api.get("/settings")).json()
            assert settings["mqtt_url"] == broker.url


async def test_a_runs_progress_is_thinned_and_ends_with_its_final_waypoint(
    tmp_path: Path,
) -> None:
    """With an interval longer than the run, the plant hears its first waypoint at once,
    then only the latest, and the final progress before the transition that ends it."""
    with mosquitto(tmp_path / "broker") as broker:
        async with (
            open_rig(
                tmp_path / "data", **broker.cell_login, cell_id=CELL, plant_progress_interval=10
            ) as rig,
            subscriber(broker.port, f"{BASE}/#") as plant,
        ):
            truth = rig.cell.bus.subscribe(4096, types=["progress"])
            final = await run(rig, "start", SPRAY_DEMO)
            assert final["state"] == "IDLE"
            # The run's own end (the start-up's INITIALIZING -> IDLE may come late too).
            await plant.wait(
                lambda: [
                    e
                    for e in plant.on(f"{BASE}/event")
                    if (e["old_state"], e["new_state"]) == ("EXECUTING_TRAJECTORY", "IDLE")
                ]
            )
            produced = []
            while truth.pending:
                produced.append((await truth.get()).data)
            waypoints = [p for p in produced if "waypoint" in p]
            total = waypoints[-1]["total"]
            assert [p["waypoint"] for p in waypoints][-1] == total > 2

    progress = plant.on(f"{BASE}/progress")
    assert 2 <= len(progress) < len(waypoints)  # thinned: fewer than the run published
    assert progress[0]["waypoint"] == 1  # the first goes at once
    assert progress[-1]["waypoint"] == total and progress[-1]["fraction"] == 1.0
    assert [p["waypoint"] for p in progress] == sorted(p["waypoint"] for p in progress)
    # On the broker, in order: the final progress, then the run, then the end of the state.
    order = [
        str(m.topic).rsplit("/", 1)[-1]
        for m in plant.messages
        if str(m.topic) in (f"{BASE}/progress", f"{BASE}/run", f"{BASE}/event")
    ]
    assert order[-3:] == ["progress", "run", "event"], order


async def test_what_happened_while_the_broker_was_away(tmp_path: Path, caplog) -> None:
    buffer = 2
    with mosquitto(tmp_path / "broker") as broker:
        async with (
            open_rig(
                tmp_path / "data",
                **broker.cell_login,
                cell_id=CELL,
                mqtt_buffer=buffer,
                mqtt_reconnect_max=0.5,
            ) as rig,
            subscriber(broker.port, f"{BASE}/#", identifier="plant", persistent=True) as plant,
        ):
            await plant.wait(
                lambda: rig.cell.view.state.value == "IDLE" and plant.on(f"{BASE}/state")
            )
            health = rig.cell.bus  # noqa: F841
            broker.stop()
            await _wait_http(rig, lambda h: h["mqtt"]["connected"] is False)
            seen_before = len(plant.messages)

            # While it is away: an e-stop and a reset, twice (transitions and the faults).
            truth = rig.cell.bus.subscribe(4096, types=BUS_TYPES)
            for _ in range(2):
                assert (await rig.api.post("/estop", json={"reason": "drill"})).status_code == 202
                await rig.wait_state("ERROR")
                assert (await rig.reset()).status_code == 202
                await rig.wait_state("IDLE")
            produced = []
            while truth.pending:
                produced.append(await truth.get())
            truth.close()
            stream = [m for m in produced if m.type != "progress"]
            assert len(stream) > buffer  # the buffer overflowed

            broker.start()
            after = await _wait_http(rig, lambda h: h["mqtt"]["connected"] is True)
            assert after["mqtt"]["dropped"] == len(stream) - buffer
            assert after["mqtt"]["reconnects"] == 1

            # The newest `buffer` stream messages come, in order; the state is the latest.
            newest_transition = [m for m in stream if m.type == "state_changed"][-1]
            events = await plant.wait(
                lambda: [
                    m
                    for m in plant.on(f"{BASE}/event")[0:]
                    if m["event_id"] == newest_transition.data["event_id"]
                ]
            )
            assert events
            arrived = [m for m in plant.messages[seen_before:] if str(m.topic) in _stream_topics()]
            expected = [_stream_key(m) for m in stream[-buffer:]]
            assert [_arrived_key(m) for m in arrived] == expected
            state = await plant.wait(
                lambda: [
                    s
                    for s in plant.on(f"{BASE}/state")
                    if s["since"] == rig.cell.view.since and s["state"] == "IDLE"
                ]
            )
            assert state
            assert any("dropped while it was away" in r.getMessage() for r in caplog.records)


async def test_no_progress_of_a_run_that_ended_while_the_broker_was_away(
    tmp_path: Path,
) -> None:
    """Progress waiting in the outbox for a run that has ended is stale: dropped, not sent
    when the broker is back; the run's end and the transitions still come, in order."""
    with mosquitto(tmp_path / "broker") as broker:
        async with (
            open_rig(
                tmp_path / "data",
                **broker.cell_login,
                cell_id=CELL,
                plant_progress_interval=0,
                mqtt_reconnect_max=0.5,
            ) as rig,
            subscriber(broker.port, f"{BASE}/#", identifier="plant", persistent=True) as plant,
        ):
            await plant.wait(
                lambda: rig.cell.view.state.value == "IDLE" and plant.on(f"{BASE}/state")
            )
            broker.stop()
            await _wait_http(rig, lambda h: h["mqtt"]["connected"] is False)
            seen_before = len(plant.messages)
            final = await run(rig, "start", SPRAY_DEMO)  # the whole run while it is away
            assert final["state"] == "IDLE"
            broker.start()
            runs = await plant.wait(lambda: plant.on(f"{BASE}/run"))
            run_id = runs[-1]["run_id"]
            await plant.wait(
                lambda: [
                    e for e in plant.on(f"{BASE}/event") if e["old_state"] == "EXECUTING_TRAJECTORY"
                ]
            )
            arrived = plant.messages[seen_before:]
            topics = [str(m.topic).rsplit("/", 1)[-1] for m in arrived]
            assert "progress" not in topics, topics
            assert [t for t in topics if t in ("event", "run")] == ["event", "run", "event"]
            assert runs[-1]["outcome"] == "completed" and run_id


def _stream_topics() -> set[str]:
    return {f"{BASE}/event", f"{BASE}/alert"}


def _stream_key(message) -> tuple[str, str]:
    if message.type == "state_changed":
        return ("event", message.data["event_id"])
    return ("alert", message.data["code"])


def _arrived_key(message: aiomqtt.Message) -> tuple[str, str]:
    data = json.loads(bytes(message.payload))
    if str(message.topic).endswith("/event"):
        return ("event", data["event_id"])
    return ("alert", data["code"])


async def _wait_http(rig, check) -> dict:
    async with asyncio.timeout(WAIT_S):
        while not check(health := (await rig.api.get("/health")).json()):
            await asyncio.sleep(0.05)
    return health


async def test_commands_need_a_valid_token_and_the_role(tmp_path: Path) -> None:
    with mosquitto(tmp_path / "broker") as broker:
        async with (
            open_rig(
                tmp_path / "data", **broker.cell_login, cell_id=CELL, mqtt_commands=True
            ) as rig,
            aiomqtt.Client(
                "127.0.0.1",
                broker.port,
                protocol=aiomqtt.ProtocolVersion.V5,
                **login_of("operator"),
            ) as requester,
        ):
            await _await_link(rig)
            tokens = {}
            for role in ("viewer", "operator"):
                made = await rig.api.post("/tokens", json={"name": f"plant-{role}", "role": role})
                tokens[role] = made.json()["token"]
            reply_to = f"{BASE}/response/{uuid.uuid4().hex}"
            await requester.subscribe(reply_to, qos=1)

            async def ask(name: str, message: object) -> tuple[dict, bytes]:
                correlation = uuid.uuid4().bytes
                properties = Properties(PacketTypes.PUBLISH)
                properties.ResponseTopic = reply_to
                properties.CorrelationData = correlation
                payload = json.dumps(message).encode()
                await requester.publish(
                    f"{BASE}/command/{name}", payload, qos=1, properties=properties
                )
                async with asyncio.timeout(WAIT_S):
                    async for answer in requester.messages:
                        got = answer.properties.CorrelationData  # type: ignore[union-attr]
                        assert got == correlation, "answers come in the order asked"
                        return json.loads(bytes(answer.payload)), got
                raise AssertionError("no answer")

            def signed(role: str, name: str, body: dict | None = None) -> dict:
                return sign_command(tokens[role], f"{BASE}/command/{name}", body)

            answer, _ = await ask("start", {"body": SPRAY_DEMO})
            assert answer["status"] == 401
            fake = "gc_00000000_" + "x" * 43
            answer, _ = await ask("start", sign_command(fake, f"{BASE}/command/start", SPRAY_DEMO))
            assert answer["status"] == 401
            answer, _ = await ask("start", signed("viewer", "start", SPRAY_DEMO))
            assert answer["status"] == 403 and "operator" in answer["detail"]
            answer, _ = await ask("start", signed("operator", "start", {"speed": 3}))
            assert answer["status"] == 422
            # Each field with its message, as HTTP's 422 has them (only the detail was sent).
            assert [e["field"] for e in answer["errors"]] == ["speed"], answer
            assert (await rig.state())["state"] == "IDLE"  # nothing of that reached the cell

            answer, _ = await ask("start", signed("operator", "start", SPRAY_DEMO))
            assert answer["status"] == 202 and answer["accepted"] is True
            assert answer["state"] == "EXECUTING_TRAJECTORY" and answer["run_id"]
            answer, _ = await ask("reset", signed("operator", "reset"))
            assert answer["status"] == 403  # a reset needs maintenance, as over HTTP

            # Any valid token may stop the cell; the stop takes the e-stop path.
            answer, _ = await ask("estop", signed("viewer", "estop", {"reason": "mqtt"}))
            assert answer["status"] == 202 and answer["state"] == "ERROR"
            snapshot = await rig.wait_state("ERROR")
            assert "mqtt" in snapshot["stop_reason"]["message"]
            answer, _ = await ask("resume", signed("operator", "resume"))
            assert answer["status"] == 409 and answer["accepted"] is False

            audit = (await rig.api.get("/audit", params={"limit": 1000})).json()["audit"]
            audit = [a for a in audit if a["action"].startswith("MQTT ")]
            rows = [(a["principal"], a["outcome"]) for a in audit]
            assert ("anonymous", "refused (401)") in rows
            assert any(p.startswith("plant-viewer") and o == "refused (403)" for p, o in rows)
            assert any(p.startswith("plant-operator") and o == "accepted" for p, o in rows)
            assert any(p.startswith("plant-viewer") and o == "accepted" for p, o in rows)
            assert all(a["action"].startswith(f"MQTT {BASE}/command/") for a in audit)


async def _await_link(rig) -> None:
    await _wait_http(rig, lambda h: h.get("mqtt", {}).get("connected") is True)


async def test_offline_when_stopped_and_when_killed(tmp_path: Path) -> None:
    env = {
        "GLUE_APP_MQTT_URL": "",
        "GLUE_APP_CELL_ID": CELL,
        "GLUE_APP_MQTT_KEEPALIVE": "1",
    }
    with mosquitto(tmp_path / "broker") as broker:
        env.update(broker.cell_environment)
        data = tmp_path / "data"
        data.mkdir()
        async with subscriber(broker.port, f"{BASE}/status") as plant:
            topic = f"{BASE}/status"

            def said() -> list[str]:
                return [s["status"] for s in plant.on(topic)]

            async with _server_process(free_port(), data, env) as server:
                await plant.wait(lambda: said()[-1:] == ["online"])
                server.send_signal(signal.SIGTERM)  # a clean stop says offline itself
                await asyncio.to_thread(server.wait, WAIT_S)
            await plant.wait(lambda: said()[-1:] == ["offline"])
            online, offline = plant.on(topic)[-2:]
            # Each with its time, as the cell's other messages; a clean stop says it is one.
            assert online["time"] < offline["time"] and offline["clean"] is True
            count = len(plant.on(topic))

            port = free_port()
            async with _server_process(port, data, env) as server:
                await plant.wait(lambda: said()[count:] == ["online"])
                token = admin_headers(data)
                async with httpx.AsyncClient(headers=token) as http:
                    health = (await http.get(f"http://127.0.0.1:{port}/health")).json()
                assert health["mqtt"]["connected"] is True
                os.kill(server.pid, signal.SIGKILL)  # no word from it: the broker's will
                await asyncio.to_thread(server.wait, WAIT_S)
                await plant.wait(lambda: said()[count:] == ["online", "offline"])
            will = plant.on(topic)[-1]
            # The will was written at connect: it cannot know when the cell fell silent.
            assert will["clean"] is False and will["time"] is None
            assert will["online_since"] == plant.on(topic)[-2]["time"]


@contextlib.asynccontextmanager
async def _server_process(
    port: int, data: Path, env: dict[str, str]
) -> AsyncIterator[subprocess.Popen[str]]:
    """`server_process`, started and stopped on a thread: its wait for the server (which
    commissions a fresh cell first) would otherwise hold this loop, and the plant's
    subscriber on it, past the broker's keep-alive, which drops the subscriber."""
    with contextlib.ExitStack() as stack:
        yield await asyncio.to_thread(stack.enter_context, server_process(port, data, env))
        await asyncio.to_thread(stack.close)


async def test_the_stop_is_answered_before_the_link_publishes_it(
    tmp_path: Path, monkeypatch
) -> None:
    """The e-stop's answer is on the wire before the link does its work for ERROR."""
    from server.core.infra.answers_in_flight import AnswersInFlight
    from server.mqtt.link import MqttLink

    log: list[str] = []
    begin, end, put_state = AnswersInFlight.begin, AnswersInFlight.end, MqttLink._put_state

    def noting_begin(self: AnswersInFlight) -> int:
        log.append("answer begins")
        return begin(self)

    def noting_end(self: AnswersInFlight, ticket: int) -> None:
        log.append("answer ends")
        end(self, ticket)

    def noting_put(self: MqttLink, changed: dict | None = None) -> None:
        if changed is not None and changed["snapshot"]["state"] == "ERROR":
            log.append("ERROR published")
        put_state(self, changed)

    monkeypatch.setattr(AnswersInFlight, "begin", noting_begin)
    monkeypatch.setattr(AnswersInFlight, "end", noting_end)
    monkeypatch.setattr(MqttLink, "_put_state", noting_put)
    await _stop_while_spraying(tmp_path, log.clear)
    # The stop's answer began and ended (its last byte handed to the socket) before
    # the link turned the transition into messages.
    assert log[:3] == ["answer begins", "answer ends", "ERROR published"], log


async def test_a_transitions_messages_do_not_wait_for_each_others_acknowledgement(
    tmp_path: Path, monkeypatch
) -> None:
    """A stop's run, state and event go out together, each still acknowledged (QoS 1):
    one at a time, the event waited two broker round trips for the two before it."""
    log: list[tuple[str, str]] = []
    publish = aiomqtt.Client.publish

    async def noting_publish(self: aiomqtt.Client, topic: str, *args, **kwargs) -> None:
        log.append(("sent", topic))
        await publish(self, topic, *args, **kwargs)
        log.append(("acknowledged", topic))

    monkeypatch.setattr(aiomqtt.Client, "publish", noting_publish)
    await _stop_while_spraying(tmp_path, log.clear)
    sent = [topic for what, topic in log if what == "sent"]
    assert f"{BASE}/state" in sent and f"{BASE}/event" in sent, log
    event_sent = log.index(("sent", f"{BASE}/event"))
    state_acknowledged = log.index(("acknowledged", f"{BASE}/state"))
    assert event_sent < state_acknowledged, log
    assert sent.index(f"{BASE}/state") < sent.index(f"{BASE}/event"), log  # still in order


async def _stop_while_spraying(tmp_path: Path, before_the_stop: Callable[[], None]) -> None:
    """A cell on a real broker, stopped on its spray path; returns once the plant has the
    stop's event. `before_the_stop` runs just before the stop is sent."""
    with mosquitto(tmp_path / "broker") as broker:
        async with (
            open_rig(tmp_path / "data", **broker.cell_login, cell_id=CELL) as rig,
            subscriber(broker.port, f"{BASE}/#") as plant,
        ):
            await rig.start_spraying()
            before_the_stop()
            assert (await rig.api.post("/estop")).status_code == 202
            await plant.wait(lambda: [e for e in plant.on(f"{BASE}/event") if e["to"] == "ERROR"])
            assert rig.robot.last_stop_at is not None and not rig.glue.valve_open


async def test_the_retained_kpis_count_a_part_as_soon_as_its_run_ends(tmp_path: Path) -> None:
    """The period is a floor, not a delay: a plant's dashboard counts the part when
    it is made, as Sparkplug B's node does, not up to `mqtt_kpis_interval` later."""
    with mosquitto(tmp_path / "broker") as broker:
        async with (
            open_rig(
                tmp_path / "data", **broker.cell_login, cell_id=CELL, mqtt_kpis_interval=3600
            ) as rig,
            subscriber(broker.port, f"{BASE}/#") as plant,
        ):
            await plant.wait(lambda: plant.on(f"{BASE}/kpis"))  # the first, at start
            assert (await run(rig, "start", SPRAY_DEMO))["state"] == "IDLE"
            quality = (await rig.api.get("/kpis")).json()["quality"]
            assert quality["parts_good"] + quality["parts_defective"] == 1, quality

            def told() -> bool:
                kpis = plant.on(f"{BASE}/kpis")
                return bool(kpis) and kpis[-1]["quality"] == quality

            await plant.wait(told)
