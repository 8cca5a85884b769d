"""clients/client/ (the package) against a real server on loopback, the core on in-process fakes.

The server runs in a thread with its own event loop, so the blocking client can
be called directly from the test and the async client from the test's loop,
while the test still reaches into the server's loop to force the awkward cases
(a full event queue, a burst that overflows a WebSocket client's buffer).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import socket
import threading
from collections.abc import Callable, Coroutine, Iterator
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import httpx
import pytest

from clients.client import (
    AsyncCellClient,
    Busy,
    CellClient,
    CellError,
    CellFaulted,
    Forbidden,
    InvalidRequest,
    MessageStream,
    NotFound,
    Refused,
    ServerError,
    Unauthorized,
    Unreachable,
    WaitTimeout,
    resolve_token,
)
from server.bootstrap.cell import Cell
from server.core.infra.bus import REPLAY_HISTORY
from server.core.machine.transitions import Event
from server.core.worker.devices import CellDevices
from server.settings.model import Settings
from tests.conftest import demo_stores, is_waypoint
from tests.fakes import FakeCamera, FakeGlue, FakeRobot
from tests.serving import admin_headers, free_port, serve

WS_BUFFER = 8  # the smallest ws_client_buffer the settings allow
MAX_WS_CLIENTS = 2


@dataclass
class Served:
    """A server running in its own thread and loop, and how to act inside that loop."""

    url: str
    cell: Cell
    loop: asyncio.AbstractEventLoop
    admin: str
    viewer: str
    baseline_subscriptions: frozenset[int]  # the bus's subscribers that are not /ws clients

    def call(self, function: Callable[[], Any]) -> Any:
        """Run `function` in the server's loop (atomically: nothing else runs meanwhile)."""
        done: concurrent.futures.Future[Any] = concurrent.futures.Future()

        def run() -> None:
            try:
                done.set_result(function())
            except BaseException as exc:
                done.set_exception(exc)

        self.loop.call_soon_threadsafe(run)
        return done.result(10)

    def run(self, coroutine: Coroutine[Any, Any, Any]) -> Any:
        return asyncio.run_coroutine_threadsafe(coroutine, self.loop).result(10)

    def publish(self, count: int, start: int = 0) -> None:
        """Publish `count` progress messages in one go, from the server's loop."""
        bus = self.cell.bus
        self.call(lambda: [bus.publish("progress", {"waypoint": start + i}) for i in range(count)])

    def drop_websockets(self, then_publish: int = 0) -> int:
        """Close every /ws client's subscription (the server closes them with 4001),
        then publish `then_publish` messages while they are away, all in one go."""
        bus = self.cell.bus

        def drop() -> int:
            clients = [s for s in bus._subscribers if id(s) not in self.baseline_subscriptions]
            for subscription in clients:
                subscription.close("dropped by the test")
            for index in range(then_publish):
                bus.publish("progress", {"while_away": index})
            return len(clients)

        return self.call(drop)


@contextlib.contextmanager
def served_in_thread(cell: Cell) -> Iterator[tuple[str, asyncio.AbstractEventLoop]]:
    """`tests.serving.serve(cell)` in a background thread; yields the URL and its loop."""
    loop = asyncio.new_event_loop()
    ready: concurrent.futures.Future[tuple[str, asyncio.Event]] = concurrent.futures.Future()

    async def main() -> None:
        try:
            async with serve(cell) as url:
                stop = asyncio.Event()
                ready.set_result((url, stop))
                await stop.wait()
        except BaseException as exc:
            if not ready.done():
                ready.set_exception(exc)
            raise

    thread = threading.Thread(target=loop.run_until_complete, args=(main(),), daemon=True)
    thread.start()
    try:
        url, stop = ready.result(30)
        yield url, loop
        loop.call_soon_threadsafe(stop.set)
    finally:
        thread.join(30)
        loop.close()


@pytest.fixture
def served(fast_settings: Settings) -> Iterator[Served]:
    settings = fast_settings.model_copy(
        update={"ws_client_buffer": WS_BUFFER, "max_broadcast_clients": MAX_WS_CLIENTS}
    )
    demo_stores(settings.data_path)
    cell = Cell(settings, devices=CellDevices(FakeRobot(speed_factor=5), FakeGlue(), FakeCamera()))
    with served_in_thread(cell) as (url, loop):
        admin = admin_headers(settings.data_path)["Authorization"].split()[1]
        with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {admin}"}) as http:
            viewer = http.post("/tokens", json={"name": "wall screen", "role": "viewer"})
            viewer.raise_for_status()
        with CellClient(url, admin) as client:
            client.wait_for_state("IDLE", 10)
        served = Served(url, cell, loop, admin, viewer.json()["token"], frozenset())
        served.baseline_subscriptions = served.call(
            lambda: frozenset(id(s) for s in cell.bus._subscribers)
        )
        yield served


@pytest.fixture
async def aclient(served: Served):
    async with AsyncCellClient(served.url, served.admin) as client:
        yield client


def settle(client: CellClient) -> None:
    """Let a started operation end; reset if it ended in ERROR (blank fake camera frames)."""
    try:
        client.wait_for_state("IDLE", 20)
    except CellFaulted:
        assert client.reset().state == "IDLE"


START = {"workpiece_id": "demo", "contour_matching": False}


# --- every method, blocking client ------------------------------------------------------


def test_the_blocking_client_drives_a_whole_cycle(served: Served) -> None:
    with CellClient(served.url, served.admin) as client:
        assert client.health()["status"] == "ok"
        assert client.state()["state"] == "IDLE"
        assert client.allowed("calibrate-robot")["allowed"] is True
        assert client.allowed("resume") == {
            "operation": "resume",
            "allowed": False,
            "state": "IDLE",
            "reason": "resume is not allowed in IDLE",
        }
        assert [w["id"] for w in client.workpieces()] == ["demo"]

        started = client.start(**START)
        assert started.accepted and started.status_code == 202 and started.event_id
        assert started.state == "EXECUTING_TRAJECTORY"
        assert started.message == "start accepted: IDLE → EXECUTING_TRAJECTORY"
        assert started.run_id == client.state()["operation"]["run_id"]
        paused = client.pause()
        assert paused.state == "PAUSED" and paused.run_id is None  # it started no run
        assert client.resume().state == "EXECUTING_TRAJECTORY"
        assert client.cancel().state == "IDLE"

        client.start(**START)
        assert client.wait_for_state("idle", 20)["state"] == "IDLE"
        latest = client.history(limit=3)
        assert len(latest) == 3
        assert (latest[0]["old_state"], latest[0]["new_state"]) == ("EXECUTING_TRAJECTORY", "IDLE")
        assert latest[0]["event"] == "OPERATION_COMPLETED"
        kpis = client.kpis()
        assert kpis["operations_completed"] >= 1 and "oee" in kpis

        stopped = client.estop(reason="door open")
        assert stopped.accepted and stopped.state == "ERROR"
        stop_reason = client.state()["stop_reason"]
        assert stop_reason["code"] == "EMERGENCY_STOP" and "door open" in stop_reason["message"]
        assert client.reset().state == "IDLE"

        assert client.calibrate_camera().state == "CALIBRATING_CAMERA"
        settle(client)
        assert client.calibrate_robot().state == "CALIBRATING_ROBOT"
        settle(client)
        # The fake camera shows no markers, so there is no robot calibration: creating a
        # part is refused before it starts, saying what to do, and nothing changes.
        with pytest.raises(Refused, match="run calibrate-robot first"):
            client.create_workpiece(name="bracket", workpiece_id="bracket")
        assert client.state()["state"] == "IDLE"


def test_health_needs_no_token(served: Served) -> None:
    with CellClient(served.url) as anonymous:
        assert anonymous.health()["status"] == "ok"
        with pytest.raises(Unauthorized):
            anonymous.state()


def test_the_blocking_client_raises_the_same_typed_errors(served: Served) -> None:
    with CellClient(served.url, served.admin) as client, pytest.raises(Refused) as refused:
        client.pause()
    assert refused.value.status_code == 409 and str(refused.value) == "pause is not allowed in IDLE"
    with CellClient(served.url, served.viewer) as viewer, pytest.raises(Forbidden) as forbidden:
        viewer.cancel()
    assert forbidden.value.status_code == 403 and "operator role" in str(forbidden.value)
    with CellClient(f"http://127.0.0.1:{free_port()}") as nowhere, pytest.raises(Unreachable):
        nowhere.health()


# --- typed errors --------------------------------------------------------------------


async def test_a_refusal_carries_the_result(aclient: AsyncCellClient) -> None:
    with pytest.raises(Refused) as refused:
        await aclient.resume()
    error = refused.value
    assert isinstance(error, CellError) and error.status_code == 409
    assert str(error) == "resume is not allowed in IDLE"
    assert error.result.accepted is False and error.result.state == "IDLE"
    assert error.result.status_code == 409 and error.result.message == str(error)


async def test_no_or_unknown_token_is_unauthorized(served: Served) -> None:
    async with AsyncCellClient(served.url) as anonymous:
        with pytest.raises(Unauthorized) as missing:
            await anonymous.state()
    assert missing.value.status_code == 401
    assert str(missing.value).startswith("authentication required")
    async with AsyncCellClient(served.url, "gc_00000000_nope") as stranger:
        with pytest.raises(Unauthorized, match="unknown or revoked"):
            await stranger.start()


async def test_a_role_too_low_is_forbidden_naming_the_role(served: Served) -> None:
    async with AsyncCellClient(served.url, served.viewer) as viewer:
        with pytest.raises(Forbidden) as forbidden:
            await viewer.start()
        assert forbidden.value.status_code == 403
        assert str(forbidden.value) == "this needs the operator role; wall screen has viewer"
        with pytest.raises(Forbidden, match="maintenance role"):
            await viewer.reset()
        assert (await viewer.estop(reason="anyone may stop")).state == "ERROR"


async def test_an_invalid_field_is_an_invalid_request_naming_it(aclient: AsyncCellClient) -> None:
    with pytest.raises(InvalidRequest) as invalid:
        await aclient.start(workpiece_id="../etc/passwd")
    assert invalid.value.status_code == 422 and "workpiece_id" in str(invalid.value)
    assert invalid.value.errors[0]["field"] == "workpiece_id"
    assert (await aclient.state())["state"] == "IDLE"
    with pytest.raises(InvalidRequest) as too_long:
        await aclient.estop(reason="x" * 201)
    assert too_long.value.errors[0]["field"] == "reason"
    # A stop is never refused over its reason: it is made, and the error says so.
    assert "stop was made" in str(too_long.value)
    assert (await aclient.state())["state"] == "ERROR"


async def test_an_unknown_operation_is_not_found(aclient: AsyncCellClient) -> None:
    with pytest.raises(NotFound) as unknown:
        await aclient.allowed("fly")
    assert unknown.value.status_code == 404 and "known operations" in str(unknown.value)
    assert isinstance(unknown.value, InvalidRequest)


async def test_a_full_queue_is_busy_with_retry_after(served: Served, aclient) -> None:
    worker = served.cell.worker
    assert worker is not None

    async def jam() -> None:
        worker._task.cancel()
        await asyncio.gather(worker._task, return_exceptions=True)
        for _ in range(worker.queue.capacity):
            worker.submit(Event.PAUSE_REQUESTED, source="test")

    served.run(jam())
    try:
        with pytest.raises(Busy) as busy:
            await aclient.pause()
    finally:
        served.call(lambda: setattr(worker, "_task", asyncio.create_task(worker._run())))
    assert busy.value.status_code == 503 and busy.value.retry_after == 1.0
    assert "queue is full" in str(busy.value)


async def test_no_server_and_a_silent_server_are_unreachable() -> None:
    async with AsyncCellClient(f"http://127.0.0.1:{free_port()}") as nowhere:
        with pytest.raises(Unreachable, match="cannot reach"):
            await nowhere.state()
    with socket.socket() as silent:  # accepts connections (backlog) but never answers
        silent.bind(("127.0.0.1", 0))
        silent.listen()
        port = silent.getsockname()[1]
        async with AsyncCellClient(f"127.0.0.1:{port}", timeout=0.3) as mute:
            with pytest.raises(
                Unreachable, match=r"no answer from http://127.0.0.1:\d+ within 0.3 s"
            ):
                await mute.state()


class NotTheCell(BaseHTTPRequestHandler):
    """Something else on the port: a 500 for /state, an HTML page for everything else."""

    def do_GET(self) -> None:
        status, body = (
            (500, b"Internal Server Error") if self.path == "/state" else (200, b"<html>")
        )
        self.send_response(status)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format: str, *args: Any) -> None:
        pass


def test_answers_the_api_does_not_document_are_server_errors() -> None:
    with ThreadingHTTPServer(("127.0.0.1", 0), NotTheCell) as other:
        threading.Thread(target=other.serve_forever, daemon=True).start()
        try:
            with CellClient(f"http://127.0.0.1:{other.server_address[1]}") as client:
                with pytest.raises(ServerError) as crashed:
                    client.state()
                assert crashed.value.status_code == 500
                assert str(crashed.value) == "Internal Server Error"
                with pytest.raises(ServerError, match="unexpected answer to GET /kpis"):
                    client.kpis()
        finally:
            other.shutdown()


# --- waiting -----------------------------------------------------------------------------


async def test_wait_for_state_times_out_naming_the_state(aclient: AsyncCellClient) -> None:
    with pytest.raises(WaitTimeout) as timeout:
        await aclient.wait_for_state("PAUSED", 0.3)
    assert str(timeout.value) == "timed out after 0.3 s waiting for PAUSED; the cell is in IDLE"
    assert timeout.value.last_state and timeout.value.last_state["state"] == "IDLE"
    with pytest.raises(ValueError, match="unknown state 'pausing'; states: INITIALIZING, IDLE"):
        await aclient.wait_for_state("pausing", 1)


async def test_wait_stops_when_the_cell_falls_into_error(aclient: AsyncCellClient) -> None:
    await aclient.start(**START)
    waiting = asyncio.create_task(aclient.wait_for_state("PAUSED", 10, poll_interval=0.02))
    await asyncio.sleep(0.1)
    await aclient.estop(reason="door open")
    with pytest.raises(CellFaulted) as faulted:
        await waiting
    assert str(faulted.value).startswith("the cell is in ERROR, waiting for PAUSED: ")
    assert "door open" in str(faulted.value)


async def test_a_wait_in_error_fails_at_once_unless_told_to_wait_through(
    aclient: AsyncCellClient,
) -> None:
    await aclient.estop()
    with pytest.raises(CellFaulted, match="the cell is in ERROR, waiting for IDLE"):
        await aclient.wait_for_state("IDLE", 10)
    waiting = asyncio.create_task(aclient.wait_for_state("IDLE", 10, fail_on=()))
    await asyncio.sleep(0.2)
    assert not waiting.done()
    await aclient.reset()
    assert (await waiting)["state"] == "IDLE"
    assert (await aclient.wait_for_state("idle", 1))["state"] == "IDLE"


# --- the /ws iterator -----------------------------------------------------------------------


async def next_message(stream: MessageStream) -> dict[str, Any]:
    return await asyncio.wait_for(anext(stream), 10)


async def test_messages_yield_the_snapshot_then_every_message_in_seq_order(
    aclient: AsyncCellClient,
) -> None:
    async with aclient.messages() as stream:
        snapshot = await next_message(stream)
        assert snapshot["type"] == "snapshot" and snapshot["state"] == "IDLE"
        assert "resumed" not in snapshot and snapshot["history"]
        await aclient.start(**START)
        messages = []
        while True:
            message = await next_message(stream)
            messages.append(message)
            if message["type"] == "state_changed" and message["new_state"] == "IDLE":
                break
    first = snapshot["seq"] + 1
    assert [m["seq"] for m in messages] == list(range(first, first + len(messages)))
    assert (
        messages[0]["type"] == "state_changed"
        and messages[0]["new_state"] == "EXECUTING_TRAJECTORY"
    )
    waypoints = [m["waypoint"] for m in messages if is_waypoint(m)]
    assert waypoints and waypoints == list(range(1, len(waypoints) + 1))
    assert stream.reconnects == 0


async def test_messages_filter_types_but_always_pass_snapshots(aclient: AsyncCellClient) -> None:
    async with aclient.messages(types=["state_changed"]) as stream:
        assert (await next_message(stream))["type"] == "snapshot"
        await aclient.start(**START)
        states = []
        while not states or states[-1] != "IDLE":
            message = await next_message(stream)
            assert message["type"] == "state_changed"
            states.append(message["new_state"])
    assert states == ["EXECUTING_TRAJECTORY", "IDLE"]


async def test_messages_resume_after_the_server_drops_a_slow_consumer(
    served: Served, aclient: AsyncCellClient
) -> None:
    async with aclient.messages() as stream:
        snapshot = await next_message(stream)
        served.publish(3)
        received = [await next_message(stream) for _ in range(3)]
        assert [m["seq"] for m in received] == [snapshot["seq"] + i for i in (1, 2, 3)]
        last_seen = received[-1]["seq"]

        # More than the client's buffer in one go, before the server can send any:
        # the hub drops the client (close 4001); the stream reconnects from the last
        # seq it saw and the server replays the burst from its ring.
        served.publish(WS_BUFFER + 12, start=100)
        resumed = await next_message(stream)
        assert resumed["type"] == "snapshot" and resumed["resumed"] is True
        assert resumed["missed"] == 0
        assert resumed["replayed"] == resumed["seq"] - last_seen >= WS_BUFFER + 12
        assert resumed["state"] == "IDLE" and "restarted" not in resumed
        assert resumed["boot"] == stream.boot == served.cell.bus.boot
        assert stream.reconnects == 1 and stream.last_close
        assert stream.last_close[0] == 4001 and "fell behind" in stream.last_close[1]
        replayed = [await next_message(stream) for _ in range(resumed["replayed"])]
        assert [m["seq"] for m in replayed] == list(range(last_seen + 1, resumed["seq"] + 1))
        assert [m["waypoint"] for m in replayed][-(WS_BUFFER + 12) :] == list(
            range(100, 100 + WS_BUFFER + 12)
        )

        served.publish(1, start=1000)
        after = await next_message(stream)
        assert after["seq"] == resumed["seq"] + 1 and after["waypoint"] == 1000


async def test_messages_are_yielded_exactly_once_across_a_drop_during_a_run(
    served: Served, aclient: AsyncCellClient
) -> None:
    """Dropped mid-run, the consumer still sees every transition and waypoint, once."""
    # A longer first backoff than the default, so more of the run goes by unseen.
    async with aclient.messages(initial_backoff=0.5) as stream:
        snapshot = await next_message(stream)
        await aclient.start(**START)
        messages = []
        while not any(m["type"] == "progress" and "waypoint" in m for m in messages):
            messages.append(await next_message(stream))
        # A message published while it is away makes sure there is something to replay.
        assert served.drop_websockets(then_publish=1) == 1
        resumed = None
        while True:
            message = await next_message(stream)
            if message["type"] == "snapshot":
                assert resumed is None, "one reconnect only"
                resumed = message
                continue
            messages.append(message)
            if message["type"] == "state_changed" and message["new_state"] == "IDLE":
                break
    assert resumed is not None and resumed["resumed"] is True and resumed["missed"] == 0
    assert resumed["replayed"] >= 1 and stream.reconnects == 1
    seqs = [m["seq"] for m in messages]
    assert seqs == list(range(snapshot["seq"] + 1, snapshot["seq"] + 1 + len(messages)))
    states = [m["new_state"] for m in messages if m["type"] == "state_changed"]
    assert states == ["EXECUTING_TRAJECTORY", "IDLE"]
    waypoints = [m["waypoint"] for m in messages if is_waypoint(m)]
    assert waypoints == list(range(1, len(waypoints) + 1)) and len(waypoints) > 1
    assert sum("while_away" in m for m in messages) == 1


async def test_a_gap_older_than_the_servers_ring_is_reported_missed(
    served: Served, aclient: AsyncCellClient
) -> None:
    async with aclient.messages() as stream:
        await next_message(stream)
        served.publish(1)
        last_seen = (await next_message(stream))["seq"]
        away = REPLAY_HISTORY + 10
        assert served.drop_websockets(then_publish=away) == 1
        resumed = await next_message(stream)
        assert resumed["type"] == "snapshot" and resumed["resumed"] is True
        assert resumed["missed"] == resumed["seq"] - last_seen >= away
        assert "replayed" not in resumed and "restarted" not in resumed
        assert stream.last_seq == resumed["seq"]
        served.publish(1, start=1000)
        after = await next_message(stream)  # no replay in between: straight to live
        assert after["seq"] == resumed["seq"] + 1 and after["waypoint"] == 1000


async def test_a_stream_resuming_from_another_boot_is_told_it_restarted(
    served: Served, aclient: AsyncCellClient
) -> None:
    async with aclient.messages() as stream:
        first = await next_message(stream)
        stream.boot = "a server that is gone"  # as if this server had restarted meanwhile
        served.drop_websockets(then_publish=2)
        resumed = await next_message(stream)
    assert resumed["resumed"] is True and resumed["restarted"] is True
    assert resumed["missed"] == resumed["seq"] >= first["seq"] + 2
    assert "replayed" not in resumed and stream.boot == first["boot"]


async def test_a_stream_that_stops_closes_its_socket(served: Served, aclient) -> None:
    stream = aclient.messages()
    await next_message(stream)
    assert (await aclient.health())["websocket_clients"] == 1
    await stream.aclose()
    async with asyncio.timeout(10):
        while (await aclient.health())["websocket_clients"] != 0:
            await asyncio.sleep(0.02)
    async for message in aclient.messages():  # a plain `break` stops it too
        assert message["type"] == "snapshot"
        break


async def test_messages_without_a_valid_token_raise_unauthorized(served: Served) -> None:
    async with AsyncCellClient(served.url) as anonymous:
        with pytest.raises(Unauthorized):
            await next_message(anonymous.messages())
    async with AsyncCellClient(served.url, served.viewer) as viewer:
        assert (await next_message(viewer.messages()))["type"] == "snapshot"


async def test_a_full_hub_at_the_first_connection_is_busy(aclient: AsyncCellClient) -> None:
    async with aclient.messages() as one, aclient.messages() as two:
        await next_message(one)
        await next_message(two)
        with pytest.raises(Busy) as busy:
            await next_message(aclient.messages())
    assert busy.value.status_code == 1013 and f"max {MAX_WS_CLIENTS}" in str(busy.value)


async def test_messages_to_nowhere_raise_unreachable_at_first() -> None:
    async with AsyncCellClient(f"http://127.0.0.1:{free_port()}") as nowhere:
        with pytest.raises(Unreachable):
            await next_message(nowhere.messages())


def test_a_resumed_snapshot_after_a_server_restart_says_so() -> None:
    stream = AsyncCellClient("http://127.0.0.1:1").messages()
    stream.last_seq = 50
    # A server without replay (no boot): the client counts the gap itself.
    assert stream._resumed({"type": "snapshot", "seq": 58})["missed"] == 8
    restarted = stream._resumed({"type": "snapshot", "seq": 3})
    assert restarted["missed"] == 3 and restarted["restarted"] is True
    # A server with replay: its marks decide, and another boot is a restart whatever the seq.
    stream.boot = "b1"
    replayed = stream._resumed({"type": "snapshot", "seq": 58, "boot": "b1", "replayed": 8})
    assert replayed["missed"] == 0 and "restarted" not in replayed
    missed = stream._resumed({"type": "snapshot", "seq": 5000, "boot": "b1", "missed": 4950})
    assert missed["missed"] == 4950 and "restarted" not in missed
    other = stream._resumed({"type": "snapshot", "seq": 80, "boot": "b2", "missed": 80})
    assert other["missed"] == 80 and other["restarted"] is True


def test_the_ws_url_keeps_the_base_path_and_scheme() -> None:
    assert (
        AsyncCellClient("https://plant.example/cell/").ws_url("abc")
        == "wss://plant.example/cell/ws?ticket=abc"
    )
    assert AsyncCellClient("localhost:8000").ws_url("t") == "ws://localhost:8000/ws?ticket=t"
    assert (
        AsyncCellClient("localhost:8000").ws_url("t", after_seq=42, boot="b1")
        == "ws://localhost:8000/ws?ticket=t&after_seq=42&boot=b1"
    )
    with pytest.raises(ValueError, match="go together"):
        AsyncCellClient("localhost:8000").ws_url("t", after_seq=42)


# --- token resolution ----------------------------------------------------------------------


def test_resolve_token_option_then_env_then_the_data_dir(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("GLUE_CELL_TOKEN", raising=False)
    monkeypatch.delenv("GLUE_APP_DATA_PATH", raising=False)
    monkeypatch.chdir(tmp_path)
    assert resolve_token(None) is None
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "admin.token").write_text("gc_default\n")
    assert resolve_token(None) == "gc_default"
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "admin.token").write_text("gc_elsewhere\n")
    monkeypatch.setenv("GLUE_APP_DATA_PATH", str(elsewhere))
    assert resolve_token(None) == "gc_elsewhere"
    assert resolve_token(None, data_dir=tmp_path / "data") == "gc_default"
    monkeypatch.setenv("GLUE_CELL_TOKEN", "gc_env")
    assert resolve_token(None, data_dir=tmp_path / "data") == "gc_env"
    assert resolve_token("gc_option") == "gc_option"
    monkeypatch.setenv("OTHER_TOKEN", "gc_other")
    assert resolve_token(None, env="OTHER_TOKEN") == "gc_other"
