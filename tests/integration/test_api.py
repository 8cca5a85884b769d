"""The HTTP API and /ws, with the core on in-process fakes: what the routes answer with the
app called in process, the WebSocket and a streamed body over a real socket."""

from __future__ import annotations

import asyncio
import json
import secrets

import httpx
import pytest
import websockets

from server.bootstrap.cell import Cell
from server.core.machine.transitions import Event, State
from server.core.worker.devices import CellDevices
from server.settings.model import Settings
from tests.conftest import START, demo_stores, is_waypoint
from tests.fakes import FakeCamera, FakeGlue, FakeRobot
from tests.serving import admin_headers, in_process, serve


def _cell(settings: Settings) -> Cell:
    """A cell on fakes with the demo part, at most 3 WebSocket clients of 8 messages each."""
    devices = CellDevices(FakeRobot(speed_factor=5), FakeGlue(), FakeCamera())
    demo_stores(settings.data_path)
    return Cell(
        settings.model_copy(update={"max_broadcast_clients": 3, "ws_client_buffer": 8}),
        devices=devices,
    )


async def _until_idle(client: httpx.AsyncClient) -> None:
    async with asyncio.timeout(10):
        while (await client.get("/state")).json()["state"] != "IDLE":
            await asyncio.sleep(0.01)


@pytest.fixture
async def api(fast_settings: Settings):
    """The app called in process: for what the routes answer."""
    cell = _cell(fast_settings)
    async with in_process(cell) as client:
        await _until_idle(client)
        client.cell = cell  # type: ignore[attr-defined]
        yield client


@pytest.fixture
async def served(fast_settings: Settings):
    """The app under uvicorn on a loopback socket: for the WebSocket and streamed bodies."""
    cell = _cell(fast_settings)
    async with (
        serve(cell) as url,
        httpx.AsyncClient(
            base_url=url, timeout=10, headers=admin_headers(fast_settings.data_path)
        ) as client,
    ):
        await _until_idle(client)
        client.cell = cell  # type: ignore[attr-defined]
        client.ws_url = url.replace("http", "ws") + "/ws"  # type: ignore[attr-defined]
        yield client


async def test_commands_answer_202_or_409_with_the_reason(api) -> None:
    accepted = await api.post("/start", json=START)
    assert accepted.status_code == 202
    body = accepted.json()
    assert body["accepted"] is True and body["state"] == "EXECUTING_TRAJECTORY" and body["event_id"]
    refused = await api.post("/calibrate-robot")
    assert refused.status_code == 409
    assert refused.json()["message"] == "calibrate-robot is not allowed in EXECUTING_TRAJECTORY"
    assert refused.json()["accepted"] is False


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({"contourMatching": True}, "contourMatching"),
        ({"contour_matching": "maybe"}, "contour_matching"),
        ({"workpiece_id": "../etc/passwd"}, "workpiece_id"),
    ],
)
async def test_an_invalid_body_gets_422_naming_the_field(api, body, field) -> None:
    response = await api.post("/start", json=body)
    assert response.status_code == 422
    assert response.json()["errors"][0]["field"] == field
    assert field in response.json()["detail"]


@pytest.mark.parametrize(
    ("body", "field"),
    [({"reason": "x" * 201}, "reason"), ({"why": "jammed"}, "why"), (b"{not json", "body")],
)
async def test_an_estop_with_an_invalid_body_still_stops_the_cell(api, body, field) -> None:
    """A stop is never refused over its optional reason: it is made, and the 422 says so."""
    assert (await api.post("/start", json=START)).status_code == 202
    if isinstance(body, bytes):
        sent = await api.post("/estop", content=body, headers={"content-type": "application/json"})
    else:
        sent = await api.post("/estop", json=body)
    assert sent.status_code == 422
    answer = sent.json()
    assert answer["errors"][0]["field"] == field
    assert answer["accepted"] is True and answer["state"] == "ERROR" and answer["event_id"]
    assert "stop was made" in answer["message"]
    assert (await api.get("/state")).json()["state"] == "ERROR"
    assert api.cell.devices.glue.valve_open is False


@pytest.mark.parametrize("content_type", [None, "text/plain"])
async def test_an_estop_whose_body_is_not_sent_as_json_still_stops_the_cell(
    api, content_type
) -> None:
    """FastAPI reads a body as JSON only under a JSON content type: otherwise it is a 422
    naming the body, and the stop is made all the same, without its reason."""
    headers = {} if content_type is None else {"content-type": content_type}
    sent = await api.post("/estop", content=b'{"reason": "jammed"}', headers=headers)
    assert sent.status_code == 422, sent.text
    answer = sent.json()
    assert answer["errors"][0]["field"] == "body"
    assert answer["accepted"] is True and answer["state"] == "ERROR"
    assert "stop was made" in answer["message"]


@pytest.mark.parametrize("streamed", [False, True])
async def test_an_estop_with_an_oversized_body_still_stops_the_cell(served, streamed) -> None:
    """Over max_request_bytes the body is not read, but the stop is made: 413 says both."""
    assert (await served.post("/start", json=START)).status_code == 202
    huge = json.dumps({"reason": "x" * 2_000_000}).encode()

    async def chunks():
        for start in range(0, len(huge), 65536):
            yield huge[start : start + 65536]

    sent = await served.post(
        "/estop",
        content=chunks() if streamed else huge,
        headers={"content-type": "application/json"},
    )
    assert sent.status_code == 413
    answer = sent.json()
    assert "bytes" in answer["detail"]
    assert answer["accepted"] is True and answer["state"] == "ERROR" and answer["event_id"]
    assert (await served.get("/state")).json()["state"] == "ERROR"
    assert served.cell.devices.glue.valve_open is False


async def test_a_small_estop_body_is_read_whole(api) -> None:
    """The stop route reads its body whole before the route sees it: the reason arrives."""
    sent = await api.post("/estop", json={"reason": "jammed part"})
    assert sent.status_code == 202
    error = (await api.get("/state")).json()["error"]
    assert "jammed part" in json.dumps(error)


async def test_malformed_json_is_a_422_not_a_500(api) -> None:
    response = await api.post(
        "/start", content=b"{not json", headers={"content-type": "application/json"}
    )
    assert response.status_code == 422


async def test_state_allowed_history_and_health(api) -> None:
    state = (await api.get("/state")).json()
    assert state["state"] == "IDLE" and state["previous_state"] == "INITIALIZING"
    assert state["operation"] is None and state["error"] is None
    allowed = (await api.get("/operations/calibrate-robot/allowed")).json()
    assert allowed == {
        "operation": "calibrate-robot",
        "allowed": True,
        "state": "IDLE",
        "reason": "calibrate-robot is allowed in IDLE (→ CALIBRATING_ROBOT)",
    }
    # A plain start matches parts on the table: this cell has no robot calibration yet.
    start = (await api.get("/operations/start/allowed")).json()
    assert start["allowed"] is False and "run calibrate-robot first" in start["reason"]
    refused = (await api.get("/operations/resume/allowed")).json()
    assert refused["allowed"] is False and refused["reason"] == "resume is not allowed in IDLE"
    unknown = await api.get("/operations/fly/allowed")
    assert unknown.status_code == 404 and "known operations" in unknown.json()["detail"]
    history = (await api.get("/history")).json()["transitions"]
    assert history[0]["old_state"] == "INITIALIZING" and history[0]["new_state"] == "IDLE"
    health = (await api.get("/health")).json()
    assert health["status"] == "ok" and set(health["devices"]) == {"robot", "glue", "camera"}


async def test_a_full_queue_answers_503_with_retry_after(api) -> None:
    worker = api.cell.worker
    worker._task.cancel()
    await asyncio.gather(worker._task, return_exceptions=True)
    for _ in range(worker.queue.capacity):
        worker.submit(Event.PAUSE_REQUESTED, source="test")
    response = await api.post("/pause")
    assert response.status_code == 503
    assert response.headers["retry-after"] == "1"
    assert "queue is full" in response.json()["message"]
    worker._task = asyncio.create_task(worker._run())


async def test_ws_sends_a_snapshot_then_every_change_in_sequence(served) -> None:
    async with websockets.connect(
        served.ws_url, additional_headers={"Authorization": served.headers["authorization"]}
    ) as ws:
        snapshot = json.loads(await ws.recv())
        assert snapshot["type"] == "snapshot" and snapshot["state"] == "IDLE"
        assert snapshot["history"] and "context" in snapshot
        await served.post("/start", json=START)
        messages = []
        async with asyncio.timeout(20):
            while True:
                message = json.loads(await ws.recv())
                messages.append(message)
                if message["type"] == "state_changed" and message["new_state"] == "IDLE":
                    break
    seqs = [m["seq"] for m in messages]
    assert seqs == list(range(snapshot["seq"] + 1, snapshot["seq"] + 1 + len(messages)))
    waypoints = [m["waypoint"] for m in messages if is_waypoint(m)]
    assert waypoints == list(range(1, 8))
    assert messages[0]["new_state"] == "EXECUTING_TRAJECTORY"


async def test_ws_subscribe_filters_types_and_ping_is_answered(served) -> None:
    async with websockets.connect(
        served.ws_url, additional_headers={"Authorization": served.headers["authorization"]}
    ) as ws:
        await ws.recv()
        await ws.send(json.dumps({"type": "subscribe", "types": ["state_changed"]}))
        assert json.loads(await ws.recv())["type"] == "subscribed"
        await ws.send(json.dumps({"type": "ping"}))
        assert json.loads(await ws.recv()) == {"type": "pong"}
        await served.post("/start", json=START)
        async with asyncio.timeout(20):
            while True:
                message = json.loads(await ws.recv())
                assert message["type"] == "state_changed"
                if message["new_state"] == "IDLE":
                    break


async def test_ws_client_sending_garbage_is_closed_with_a_code(served) -> None:
    async with websockets.connect(
        served.ws_url, additional_headers={"Authorization": served.headers["authorization"]}
    ) as ws:
        await ws.recv()
        await ws.send("this is not json")
        with pytest.raises(websockets.ConnectionClosed) as closed:
            await asyncio.wait_for(ws.recv(), 5)
    assert closed.value.rcvd.code == 1003
    assert (await served.get("/health")).status_code == 200


async def test_ws_over_the_client_limit_is_refused_with_a_code(served) -> None:
    clients = [
        await websockets.connect(
            served.ws_url, additional_headers={"Authorization": served.headers["authorization"]}
        )
        for _ in range(3)
    ]
    try:
        for ws in clients:
            await ws.recv()
        extra = await websockets.connect(
            served.ws_url, additional_headers={"Authorization": served.headers["authorization"]}
        )
        with pytest.raises(websockets.ConnectionClosed) as closed:
            await asyncio.wait_for(extra.recv(), 5)
        assert closed.value.rcvd.code == 1013 and "max 3" in closed.value.rcvd.reason
    finally:
        for ws in clients:
            await ws.close()


async def test_a_client_that_never_reads_is_dropped_and_others_keep_receiving(served) -> None:
    worker = served.cell.worker
    async with (
        websockets.connect(
            served.ws_url,
            additional_headers={"Authorization": served.headers["authorization"]},
            max_queue=1,
        ) as stuck,
        websockets.connect(
            served.ws_url, additional_headers={"Authorization": served.headers["authorization"]}
        ) as healthy,
    ):
        await stuck.recv()
        await healthy.recv()
        stuck.transport.pause_reading()  # never read again
        subscribers = served.cell.bus.subscriber_count  # both clients, and the metrics
        sent = 0
        while served.cell.bus.subscriber_count == subscribers and sent < 4000:
            for _ in range(4):  # bursts within the healthy client's buffer of 8
                worker.bus.publish(
                    "progress", {"waypoint": sent, "padding": secrets.token_hex(10_000)}
                )
                sent += 1
            for index in range(sent - 4, sent):
                assert json.loads(await healthy.recv())["waypoint"] == index
        dropped = served.cell.bus.subscriber_count == subscribers - 1
        assert dropped, "the stuck client was not dropped"
        worker.bus.publish("progress", {"waypoint": "after"})
        assert json.loads(await healthy.recv())["waypoint"] == "after"
        assert worker.ctx.state is State.IDLE
