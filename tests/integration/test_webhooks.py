"""Webhooks against a real receiver on loopback: signed notices of a fault, of every
state change of a run and of its completion; retries of 5xx, none of a 400; a dead
receiver that never holds up the e-stop or a transition, with its queue bounded and
its drops counted; and the admin routes that show all this to admins only."""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import hmac
import json
import socket
from collections import deque
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from typing import Any

import pytest
import uvicorn

from tests.rig import SPRAY_DEMO, WAIT_S, Rig, open_rig, run
from tests.serving import free_port

SECRET = "a-secret-of-the-plant-0123456789"


@pytest.fixture(scope="module")
def cell_data(tmp_path_factory: pytest.TempPathFactory):
    """One data directory for the module: the simulated cell is commissioned once."""
    return tmp_path_factory.mktemp("cell")


@dataclass(frozen=True)
class Post:
    headers: dict[str, str]
    body: bytes

    @property
    def json(self) -> dict[str, Any]:
        return json.loads(self.body)


class Receiver:
    """A plain ASGI app that keeps every POST and answers with the next scripted status."""

    def __init__(self, statuses: list[int] | None = None) -> None:
        self.posts: list[Post] = []
        self._statuses = deque(statuses or [])

    async def __call__(self, scope: dict, receive: Callable, send: Callable) -> None:
        assert scope["type"] == "http"
        body = b""
        while True:
            message = await receive()
            body += message.get("body", b"")
            if not message.get("more_body"):
                break
        headers = {k.decode().lower(): v.decode() for k, v in scope["headers"]}
        self.posts.append(Post(headers, body))
        status = self._statuses.popleft() if self._statuses else 200
        await send({"type": "http.response.start", "status": status, "headers": []})
        await send({"type": "http.response.body", "body": b""})

    def notices(self, kind: str | None = None) -> list[dict[str, Any]]:
        return [p.json for p in self.posts if kind is None or p.json["kind"] == kind]


@contextlib.asynccontextmanager
async def receiving(receiver: Receiver) -> AsyncIterator[str]:
    """Serve `receiver` on a free loopback port; yields its URL."""
    port = free_port()
    config = uvicorn.Config(receiver, host="127.0.0.1", port=port, log_level="warning")
    config.lifespan = "off"
    server = uvicorn.Server(config)
    server.install_signal_handlers = lambda: None  # type: ignore[method-assign]
    task = asyncio.create_task(server.serve())
    async with asyncio.timeout(WAIT_S):
        while not server.started:
            await asyncio.sleep(0.01)
    try:
        yield f"http://127.0.0.1:{port}/hooks/glue?token=in-the-path"
    finally:
        server.should_exit = True
        await asyncio.wait_for(task, 20)


def signed_with(post: Post, secret: str) -> bool:
    """The receiver's check (docs/plant-integration.md): HMAC-SHA256 of `<timestamp>.<body>`."""
    timestamp = post.headers["x-glue-timestamp"]
    expected = hmac.new(secret.encode(), timestamp.encode() + b"." + post.body, hashlib.sha256)
    return hmac.compare_digest(post.headers["x-glue-signature"], f"sha256={expected.hexdigest()}")


async def until(predicate: Callable[[], Any], timeout: float = WAIT_S) -> Any:
    async with asyncio.timeout(timeout):
        while not (found := predicate()):
            await asyncio.sleep(0.01)
    return found


async def deliveries(rig: Rig, **filters: str) -> list[dict[str, Any]]:
    answer = await rig.api.get("/webhooks/deliveries", params=filters)
    assert answer.status_code == 200, answer.text
    return answer.json()["webhook_deliveries"]


async def leave_idle(rig: Rig) -> None:
    """Reset after an e-stop, so the next test's cell starts IDLE (the directory is shared)."""
    assert (await rig.reset()).status_code == 202
    await rig.wait_state("IDLE")


# The receivers run on 127.0.0.1, which the webhook destination policy refuses unless
# allowed: every rig here allows loopback explicitly, as a lab would.
RECEIVER_ON_THIS_HOST: dict[str, Any] = {"webhook_allowed_networks": ["127.0.0.0/8"]}


def hook(url: str, name: str, events: list[str], **extra: Any) -> dict[str, Any]:
    return {"name": name, "url": url, "events": events, "secret": SECRET, **extra}


async def test_a_run_and_an_estop_are_posted_signed_in_order(cell_data) -> None:
    receiver = Receiver()
    async with receiving(receiver) as url:
        webhooks = [hook(url, "mes", ["fault", "state", "run_completed"])]
        async with open_rig(
            cell_data, webhooks=webhooks, **RECEIVER_ON_THIS_HOST, cell_id="line1-cell2"
        ) as rig:
            # The start-up's own change into IDLE is told too; the run's come after it.
            await until(lambda: [n for n in receiver.notices("state") if n["new_state"] == "IDLE"])
            started = len(receiver.posts)
            await run(rig, "start", SPRAY_DEMO)
            await until(lambda: receiver.notices("run_completed"))
            await until(lambda: receiver.notices("state")[-1]["new_state"] == "IDLE")
            stopped = await rig.api.post("/estop")
            assert stopped.status_code in (200, 202), stopped.text
            await until(lambda: receiver.notices("fault"))
            await until(lambda: receiver.notices("state")[-1]["new_state"] == "ERROR")
            history = (await rig.api.get("/history", params={"limit": 10})).json()["transitions"]
            run_posts = receiver.posts[started:]
            await leave_idle(rig)

    kinds = [(p.json["kind"], p.json["state"]) for p in run_posts]
    # The run: each state change in order, its completion before the change back to IDLE.
    assert kinds == [
        ("state", "EXECUTING_TRAJECTORY"),
        ("run_completed", "EXECUTING_TRAJECTORY"),
        ("state", "IDLE"),
        ("fault", "ERROR"),
        ("state", "ERROR"),
    ], kinds
    notices = [p.json for p in run_posts]
    states = [(n["old_state"], n["new_state"]) for n in notices if n["kind"] == "state"]
    assert states == [(t["old_state"], t["new_state"]) for t in reversed(history[:3])]
    [completed] = [n for n in notices if n["kind"] == "run_completed"]
    assert completed["operation"] == "trajectory" and completed["workpieces"] == 1
    assert completed["run_id"] and completed["result"] is not None
    # Inspected: the notice carries the verdict and reasons of the run's inspection summary.
    inspection = completed["inspection"]
    assert completed["verdict"] == inspection["verdict"] in ("good", "defective")
    assert completed["reasons"] == inspection["reasons"]
    [fault] = [n for n in notices if n["kind"] == "fault"]
    assert fault["code"] == "EMERGENCY_STOP" and fault["component"]
    for post in run_posts:
        body = post.json
        assert body["cell_id"] == "line1-cell2" and isinstance(body["at"], float)
        assert post.headers["x-glue-delivery"] == body["id"]
        assert post.headers["x-glue-event"] == body["kind"]
        assert post.headers["content-type"] == "application/json"
        assert signed_with(post, SECRET)
        assert not signed_with(post, SECRET.replace("a-secret", "b-secret"))
        tampered = Post(post.headers, post.body.replace(b'"line1-cell2"', b'"line1-cell3"'))
        assert not signed_with(tampered, SECRET)
    assert len({p.json["id"] for p in receiver.posts}) == len(receiver.posts)


async def test_5xx_is_retried_until_delivered_and_a_400_is_not_retried(cell_data) -> None:
    flaky, strict = Receiver([500, 500, 200]), Receiver([400])
    async with receiving(flaky) as flaky_url, receiving(strict) as strict_url:
        webhooks = [hook(flaky_url, "flaky", ["fault"]), hook(strict_url, "strict", ["fault"])]
        settings = {"webhook_retry_delay": 0.05, "webhook_max_attempts": 5}
        async with open_rig(
            cell_data, webhooks=webhooks, **RECEIVER_ON_THIS_HOST, **settings
        ) as rig:
            assert (await rig.api.post("/estop")).status_code in (200, 202)
            await rig.wait_state("ERROR")
            flaky_rows = await until_rows(rig, webhook="flaky")
            strict_rows = await until_rows(rig, webhook="strict")
            status = (await rig.api.get("/webhooks")).json()
            await leave_idle(rig)

    assert len(flaky.posts) == 3
    assert len({p.headers["x-glue-delivery"] for p in flaky.posts}) == 1  # one notice, 3 tries
    assert all(signed_with(p, SECRET) for p in flaky.posts)
    [row] = flaky_rows
    assert row["outcome"] == "delivered" and row["attempts"] == 3 and row["status"] == 200
    assert [t["status"] for t in row["tries"]] == [500, 500, 200]
    assert row["tries"][0]["error"] == "HTTP 500 Internal Server Error"
    assert row["delivery_id"] == flaky.posts[0].json["id"] and row["kind"] == "fault"
    assert len(strict.posts) == 1  # a 400 is the receiver's verdict: never sent again
    [row] = strict_rows
    assert (row["outcome"], row["attempts"], row["status"]) == ("refused", 1, 400)
    counters = {w["name"]: w for w in status["webhooks"]}
    assert counters["flaky"]["delivered"] == 1 and counters["strict"]["refused"] == 1


async def until_rows(rig: Rig, **filters: str) -> list[dict[str, Any]]:
    async with asyncio.timeout(WAIT_S):
        while not (rows := await deliveries(rig, **filters)):
            await asyncio.sleep(0.05)
    return rows


async def test_a_dead_receiver_never_holds_up_the_stop_and_its_queue_is_bounded(
    cell_data,
) -> None:
    dead = f"http://127.0.0.1:{free_port()}/hook"  # nothing listens there
    webhooks = [hook(dead, "dead", ["fault", "alert", "state", "run_completed"])]
    # Every notice retried for minutes: the first stays in flight, the rest queue up.
    settings = {
        "webhook_queue_size": 2,
        "webhook_max_attempts": 50,
        "webhook_retry_delay": 30.0,
        "webhook_retry_max_delay": 60.0,
    }
    async with open_rig(cell_data, webhooks=webhooks, **RECEIVER_ON_THIS_HOST, **settings) as rig:
        first = await until_in_flight(rig)
        assert first["delivered"] == 0
        await rig.start_spraying()
        assert (await rig.api.post("/estop")).status_code in (200, 202)
        await rig.wait_state("ERROR")
        assert not rig.glue.valve_open
        assert (await rig.reset()).status_code == 202
        await rig.wait_state("IDLE")
        final = await run(rig, "start", SPRAY_DEMO)
        assert final["state"] == "IDLE"
        status = (await rig.api.get("/webhooks")).json()["webhooks"][0]
        # Every transition happened while the first notice was still failing.
        assert status["in_flight"]["delivery_id"] == first["in_flight"]["delivery_id"]
        assert status["delivered"] == 0 and status["queued"] == 2 and status["queue_size"] == 2
        assert status["dropped"] >= 5, status
        dropped = await deliveries(rig, webhook="dead", outcome="dropped")
        assert len(dropped) == status["dropped"]
        assert {row["attempts"] for row in dropped} == {0}
    # Stopped: what was in flight or queued is on record as abandoned, with its tries.
    async with open_rig(cell_data) as rig:
        abandoned = await deliveries(rig, webhook="dead", outcome="abandoned")
        assert len(abandoned) == 3
        tried = [row for row in abandoned if row["attempts"]]
        assert tried and "ConnectError" in tried[0]["tries"][0]["error"]


async def until_in_flight(rig: Rig) -> dict[str, Any]:
    """Until the start-up's notice is failing: in flight, with a failed try."""
    async with asyncio.timeout(WAIT_S):
        while True:
            status = (await rig.api.get("/webhooks")).json()["webhooks"][0]
            if status["in_flight"] and status["in_flight"]["attempts"] >= 1:
                assert "ConnectError" in status["in_flight"]["last_error"], status
                return status
            await asyncio.sleep(0.02)


async def test_the_webhooks_are_shown_to_admins_only_and_never_their_secrets(
    cell_data, tmp_path
) -> None:
    secret_file = tmp_path / "hook.secret"
    secret_file.write_text("from-a-file-0123456789abcdef\n", encoding="utf-8")
    url = f"http://127.0.0.1:{free_port()}/hooks/T0123/B0456/path-token?key=query-token"
    webhooks = [
        hook(url, "inline", ["fault"]),
        {"url": url, "events": ["state"], "secret_file": str(secret_file)},
    ]
    async with open_rig(cell_data, webhooks=webhooks, **RECEIVER_ON_THIS_HOST) as rig:
        created = await rig.api.post("/tokens", json={"name": "op", "role": "operator"})
        operator = {"Authorization": f"Bearer {created.json()['token']}"}
        for path in ("/webhooks", "/webhooks/deliveries"):
            assert (await rig.api.get(path, headers=operator)).status_code == 403
        shown = (await rig.api.get("/webhooks")).text
        settings = (await rig.api.get("/settings")).text
        listed = json.loads(shown)["webhooks"]
    for text in (shown, settings):
        assert SECRET not in text and "from-a-file" not in text
        assert "path-token" not in text and "query-token" not in text
    assert [(w["name"], w["secret_from"]) for w in listed] == [
        ("inline", "secret"),
        ("webhook-2", "secret_file"),
    ]
    assert listed[0]["url"] == f"{url.split('/hooks')[0]}/..."


async def test_a_host_name_that_resolves_to_this_host_is_refused_at_delivery(cell_data) -> None:
    """A name passes the load check (it is not resolved while the cell starts); each
    connection resolves it and refuses an address in a refused range, once, without a
    retry, before anything is sent (DNS rebinding to the cell itself)."""
    host = socket.gethostname()
    addresses = {info[4][0] for info in socket.getaddrinfo(host, None)}
    assert addresses, f"this test needs the host name {host!r} to resolve"
    receiver = Receiver()
    async with receiving(receiver) as url:
        port = url.split(":")[2].split("/")[0]
        webhooks = [hook(f"http://{host}:{port}/hooks/glue?token=secret-query", "self", ["state"])]
        # No webhook_allowed_networks: this host's own addresses are refused.
        async with open_rig(cell_data, webhooks=webhooks, webhook_max_attempts=5) as rig:
            rows = await until_rows(rig, webhook="self")
    for row in rows:
        assert (row["outcome"], row["attempts"], row["status"]) == ("refused", 1, None)
        assert "destination policy" in row["error"] and "webhook_allowed_networks" in row["error"]
        assert "secret-query" not in row["error"]
    assert receiver.posts == []
