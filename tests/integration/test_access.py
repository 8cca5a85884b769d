"""Who may do what: every route × every role, tokens, WebSocket tickets, the audit trail."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import stat
import time

import httpx
import pytest
import websockets
from fastapi.routing import APIRoute
from starlette.routing import Route

from server.bootstrap.app import create_app
from server.bootstrap.cell import Cell
from server.core.worker.devices import CellDevices
from server.security.policy import POLICY, required_role
from server.security.tickets import TicketBook
from server.security.tokens import Principal, Role, TokenStore
from server.settings.model import Settings
from tests.conftest import demo_stores
from tests.fakes import FakeCamera, FakeGlue, FakeRobot
from tests.serving import admin_headers, serve

ROLES = ("viewer", "operator", "maintenance", "admin")


@pytest.fixture
async def server(fast_settings: Settings):
    """The app on fakes, with one token per role; yields (client, tokens, settings)."""
    demo_stores(fast_settings.data_path)
    cell = Cell(fast_settings, devices=CellDevices(FakeRobot(50), FakeGlue(), FakeCamera()))
    async with serve(cell) as url, httpx.AsyncClient(base_url=url, timeout=10) as client:
        admin = admin_headers(fast_settings.data_path)
        tokens = {"admin": admin["Authorization"].split()[1]}
        for role in ROLES[:3]:
            created = await client.post("/tokens", json={"name": role, "role": role}, headers=admin)
            tokens[role] = created.json()["token"]
        client.tokens = tokens  # type: ignore[attr-defined]
        client.cell = cell  # type: ignore[attr-defined]
        yield client


def auth(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def app_routes() -> list[tuple[str, str]]:
    """Every (method, path) the app serves over HTTP, included routers' routes too.

    FastAPI (0.16x) keeps an included router as one entry of `app.routes` whose
    routes are reached through `effective_route_contexts`; plain routes (the
    API docs, the dashboard) are entries of their own.
    """
    app = create_app(Settings())
    found: set[tuple[str, str]] = set()
    for route in app.routes:
        contexts = getattr(route, "effective_route_contexts", None)
        if contexts is not None:
            found.update((m, c.path) for c in contexts() for m in (c.methods or ()))
        elif isinstance(route, APIRoute | Route):
            found.update((m, route.path) for m in (route.methods or ()))
    return sorted((method, path) for method, path in found if method != "HEAD")


def test_every_route_has_a_declared_role_and_every_declared_role_a_route() -> None:
    routes = app_routes()
    undeclared = [route for route in routes if route not in POLICY]
    assert undeclared == [], "add these routes to server/security/policy.py"
    stale = [route for route in POLICY if route not in routes]
    assert stale == [], "these policy entries name no route"


def example_path(path: str) -> str:
    return (
        path.replace("{name}", "start")
        .replace("{workpiece_id}", "demo")
        .replace("{table}", "events")
        .replace("{token_id}", "00000000")
    )


async def test_every_route_for_every_role(server) -> None:
    """No token → 401; too low a role → 403 naming the role; enough → anything but 401/403."""
    skip = {("DELETE", "/tokens/{token_id}")}  # revoking is checked on its own below
    for method, path in app_routes():
        if (method, path) in skip:
            continue
        needed = required_role(method, path)
        url = example_path(path)
        body = {} if method in ("POST", "PUT", "PATCH") else None
        anonymous = await server.request(method, url, json=body)
        if needed is None:
            assert anonymous.status_code not in (401, 403), (method, path)
            continue
        assert anonymous.status_code == 401, (method, path, anonymous.status_code)
        assert anonymous.headers["www-authenticate"] == "Bearer"
        for role in ROLES:
            response = await server.request(
                method, url, json=body, headers=auth(server.tokens[role])
            )
            if Role.parse(role) >= needed:
                assert response.status_code not in (401, 403), (method, path, role)
            else:
                assert response.status_code == 403, (method, path, role)
                assert f"needs the {needed.label} role" in response.json()["detail"]


async def test_estop_is_allowed_to_every_authenticated_role(server) -> None:
    for role in ROLES:
        response = await server.post("/estop", headers=auth(server.tokens[role]))
        assert response.status_code == 202, role
    assert (await server.post("/estop")).status_code == 401


async def test_revocation_takes_effect_immediately(server) -> None:
    operator = auth(server.tokens["operator"])
    assert (await server.get("/state", headers=operator)).status_code == 200
    listed = (await server.get("/tokens", headers=auth(server.tokens["admin"]))).json()["tokens"]
    token_id = next(t["id"] for t in listed if t["name"] == "operator")
    assert all("secret" not in key for t in listed for key in t)  # no secrets, no hashes
    revoked = await server.delete(f"/tokens/{token_id}", headers=auth(server.tokens["admin"]))
    assert revoked.status_code == 204
    refused = await server.get("/state", headers=operator)
    assert refused.status_code == 401 and "revoked" in refused.json()["detail"]


async def test_the_last_admin_token_cannot_be_revoked_and_a_second_one_frees_it(server) -> None:
    """Revoking the only admin token answered 204 and left nobody able to make or revoke
    a token; with no other token every route, the software STOP included, was closed."""
    admin = auth(server.tokens["admin"])
    listed = (await server.get("/tokens", headers=admin)).json()["tokens"]
    first = next(t["id"] for t in listed if t["role"] == "admin")
    refused = await server.delete(f"/tokens/{first}", headers=admin)
    assert refused.status_code == 409, refused.text
    assert "last admin token" in refused.json()["detail"]
    assert "POST /tokens" in refused.json()["detail"]
    assert (await server.get("/tokens", headers=admin)).status_code == 200  # still works
    audit = (await server.get("/audit", params={"outcome": "refused (409)"}, headers=admin)).json()
    assert any("last admin token" in (row["detail"] or "") for row in audit["audit"])
    second = await server.post("/tokens", json={"name": "admin 2", "role": "admin"}, headers=admin)
    assert (await server.delete(f"/tokens/{first}", headers=admin)).status_code == 204
    again = auth(second.json()["token"])
    last = await server.delete(f"/tokens/{second.json()['id']}", headers=again)
    assert last.status_code == 409


def test_a_restart_with_every_admin_token_revoked_makes_a_recovery_token(tmp_path) -> None:
    """A tokens.json from before that refusal (or edited by hand) with no admin token left:
    the server started and refused every request, and said nothing."""
    store = TokenStore(tmp_path)
    assert store.ensure_admin() == tmp_path / "admin.token"
    first = (tmp_path / "admin.token").read_text().strip()
    store.create("line HMI", Role.OPERATOR)
    entries = json.loads((tmp_path / "tokens.json").read_text())
    for entry in entries["tokens"]:
        if entry["role"] == "admin":
            entry["revoked_at"] = time.time()
    (tmp_path / "tokens.json").write_text(json.dumps(entries))
    restarted = TokenStore(tmp_path)
    assert restarted.verify(first) is None
    assert restarted.ensure_admin() == tmp_path / "admin.token"
    recovered = restarted.verify((tmp_path / "admin.token").read_text().strip())
    assert recovered is not None and recovered.role is Role.ADMIN
    assert recovered.name == "recovery admin"
    assert TokenStore(tmp_path).ensure_admin() is None  # one admin is enough


async def test_the_admin_token_file_is_private_and_tokens_are_stored_hashed(
    server, fast_settings
) -> None:
    token_file = fast_settings.data_path / "admin.token"
    assert stat.S_IMODE(os.stat(token_file).st_mode) == 0o600
    store = (fast_settings.data_path / "tokens.json").read_text()
    for token in server.tokens.values():
        assert token not in store and token.split("_", 2)[2] not in store  # the secret part


async def test_websocket_needs_a_ticket_used_once_or_a_bearer_token(server) -> None:
    url = str(server.base_url).replace("http", "ws") + "/ws"
    async with websockets.connect(url) as anonymous:
        with pytest.raises(websockets.ConnectionClosed) as closed:
            await asyncio.wait_for(anonymous.recv(), 5)
    assert closed.value.rcvd.code == 4401
    ticket = (await server.post("/ws-ticket", headers=auth(server.tokens["viewer"]))).json()
    assert 0 < ticket["expires_in_s"] <= 30
    async with websockets.connect(f"{url}?ticket={ticket['ticket']}") as viewer:
        assert (await viewer.recv()).startswith('{"type":"snapshot"')
    async with websockets.connect(f"{url}?ticket={ticket['ticket']}") as replay:
        with pytest.raises(websockets.ConnectionClosed) as closed:
            await asyncio.wait_for(replay.recv(), 5)
    assert closed.value.rcvd.code == 4401  # a ticket works once
    async with websockets.connect(url, additional_headers=auth(server.tokens["viewer"])) as ws:
        assert '"snapshot"' in await ws.recv()


async def test_a_forged_ticket_is_refused(server) -> None:
    url = str(server.base_url).replace("http", "ws") + "/ws"
    ticket = (await server.post("/ws-ticket", headers=auth(server.tokens["viewer"]))).json()
    async with websockets.connect(f"{url}?ticket={ticket['ticket']}x") as forged:
        with pytest.raises(websockets.ConnectionClosed) as closed:
            await asyncio.wait_for(forged.recv(), 5)
    assert closed.value.rcvd.code == 4401


def test_a_ticket_expires() -> None:
    book = TicketBook(ttl=0.05)
    principal = Principal("t1", "viewer", Role.VIEWER)
    fresh, _ = book.issue(principal)
    stale, _ = book.issue(principal)
    assert book.redeem(fresh) == principal
    time.sleep(0.1)
    assert book.redeem(stale) is None


async def test_the_audit_trail_records_commands_admin_actions_and_refusals(server) -> None:
    admin = auth(server.tokens["admin"])
    await server.post("/start")  # anonymous: refused
    await server.post("/calibrate-robot", headers=auth(server.tokens["operator"]))  # 403
    await server.post("/pause", headers=auth(server.tokens["operator"]))  # 409
    await server.patch("/settings", json={"error_state_timeout": 120}, headers=admin)
    await asyncio.sleep(0.2)  # the gate's refusals are written behind the answer
    rows = (await server.get("/audit", headers=admin)).json()["audit"]
    by_action = {(r["action"], r["outcome"]): r for r in rows}
    anonymous = by_action[("POST /start", "refused (401)")]
    assert anonymous["principal"] == "anonymous" and anonymous["address"] == "127.0.0.1"
    forbidden = by_action[("POST /calibrate-robot", "refused (403)")]
    assert forbidden["principal"].startswith("operator (operator")
    assert "needs the maintenance role" in forbidden["detail"]
    paused = by_action[("POST /pause", "refused (409)")]
    assert paused["detail"].startswith("event ") and "pause is not allowed in" in paused["detail"]
    change = by_action[("PATCH /settings", "accepted")]
    assert change["detail"] == "error_state_timeout: 300.0 -> 120.0"
    created = [r for r in rows if r["action"] == "POST /tokens"]
    assert created and all("gc_" not in r["detail"] for r in created)  # secrets never written


async def test_each_action_has_one_audit_row_and_the_observer_adds_none(server) -> None:
    """Commands and admin changes write their row before the answer; the observer, which
    writes the refusals, must not add a second one."""
    admin = auth(server.tokens["admin"])
    token = await server.post("/tokens", json={"name": "once", "role": "viewer"}, headers=admin)
    token_id = token.json()["id"]
    assert (await server.delete(f"/tokens/{token_id}", headers=admin)).status_code == 204
    assert (await server.patch("/settings", json={"shift_hours": 7}, headers=admin)).is_success
    part = {"name": "once", "outline_mm": [[0, 0], [10, 0], [10, 10]]}
    assert (await server.put("/workpieces/once", json=part, headers=admin)).is_success
    assert (await server.delete("/workpieces/once", headers=admin)).status_code == 204
    home = (await server.post("/home", headers=admin)).json()
    paused = (await server.post("/pause", headers=admin)).json()  # refused: 409
    await asyncio.sleep(0.2)  # anything the observer would add goes out behind the answer
    rows = (await server.get("/audit", params={"limit": 1000}, headers=admin)).json()["audit"]

    def rows_of(action: str, fragment: str) -> list[tuple[str, str]]:
        return [
            (r["outcome"], r["detail"])
            for r in rows
            if r["action"] == action and fragment in r["detail"]
        ]

    assert rows_of("POST /tokens", token_id) == [
        ("accepted", f"created token {token_id} (once, viewer)")
    ]
    assert rows_of(f"DELETE /tokens/{token_id}", "") == [
        ("accepted", f"revoked token {token_id} (once)")
    ]
    assert rows_of("PATCH /settings", "shift_hours") == [("accepted", "shift_hours: 8.0 -> 7.0")]
    assert rows_of("PUT /workpieces/once", "") == [("accepted", "stored workpiece once (once)")]
    assert rows_of("DELETE /workpieces/once", "") == [("accepted", "deleted workpiece once")]
    assert [o for o, _ in rows_of("POST /home", home["event_id"])] == ["accepted"]
    assert [o for o, _ in rows_of("POST /pause", paused["event_id"])] == ["refused (409)"]


async def test_a_refusals_audit_row_says_why(server) -> None:
    """A refused settings change or library edit left an audit row with an empty detail."""
    admin = auth(server.tokens["admin"])
    bad = await server.patch("/settings", json={"shift_hours": -1}, headers=admin)
    assert bad.status_code == 422
    missing = await server.delete("/workpieces/no-such-part", headers=admin)
    assert missing.status_code == 404
    await asyncio.sleep(0.2)  # the observer's rows go out behind the answers
    rows = (await server.get("/audit", params={"limit": 1000}, headers=admin)).json()["audit"]
    details = {r["action"]: r["detail"] for r in rows if r["outcome"].startswith("refused")}
    assert "shift_hours" in details["PATCH /settings"], details
    assert "'no-such-part' is not in the library" in details["DELETE /workpieces/no-such-part"]


async def test_settings_changes_are_validated_and_limited(server) -> None:
    admin = auth(server.tokens["admin"])
    bad = await server.patch("/settings", json={"error_state_timeout": -1}, headers=admin)
    assert bad.status_code == 422 and "error_state_timeout" in bad.json()["detail"]
    fixed = await server.patch("/settings", json={"robot_ip": "10.0.0.1"}, headers=admin)
    assert fixed.status_code == 422 and "robot_ip" in fixed.json()["detail"]
    settings = (await server.get("/settings", headers=admin)).json()
    assert settings["error_state_timeout"] == 300.0


async def test_an_oversized_body_is_refused_with_413(server) -> None:
    admin = auth(server.tokens["admin"])
    huge = {"name": "x", "outline_mm": [[0.0, 0.0]] * 200_000}
    response = await server.post("/workpieces", json=huge, headers=admin)
    assert response.status_code == 413

    async def chunks():
        for _ in range(2000):
            yield b"x" * 1024

    streamed = await server.post(
        "/workpieces", content=chunks(), headers={**admin, "content-type": "application/json"}
    )
    assert streamed.status_code == 413


async def test_an_oversized_body_is_on_record_as_refused(server) -> None:
    """A 413 is a refusal like the others (docs/security.md): its audit row says why. The
    body limit sat outside the response observers, and no row was written."""
    admin = auth(server.tokens["admin"])
    huge = {"name": "x", "outline_mm": [[0.0, 0.0]] * 200_000}
    assert (await server.post("/workpieces", json=huge, headers=admin)).status_code == 413
    async with asyncio.timeout(5):  # the observer's row goes out behind the answer
        while True:
            query = {"outcome": "refused (413)"}
            rows = (await server.get("/audit", params=query, headers=admin)).json()["audit"]
            if rows:
                break
            await asyncio.sleep(0.01)
    assert rows[0]["action"] == "POST /workpieces"
    assert "(admin," in rows[0]["principal"] and "bytes" in rows[0]["detail"]


async def test_trusted_networks_close_the_api_to_other_addresses(fast_settings) -> None:
    settings = fast_settings.model_copy(update={"trusted_networks": ["10.0.0.0/8"]})
    cell = Cell(settings, devices=CellDevices(FakeRobot(50), FakeGlue(), FakeCamera()))
    async with serve(cell) as url, httpx.AsyncClient(base_url=url) as client:
        response = await client.get("/state", headers=admin_headers(settings.data_path))
        assert response.status_code == 403 and "not allowed" in response.json()["detail"]


async def test_the_audit_trail_filters_and_exports(server) -> None:
    admin = auth(server.tokens["admin"])
    await server.post("/start")
    await asyncio.sleep(0.2)
    rows = (await server.get("/audit", params={"action": "POST /start"}, headers=admin)).json()
    assert rows["total"] >= 1 and {r["action"] for r in rows["audit"]} == {"POST /start"}
    export = await server.get("/audit.csv", params={"outcome": "refused (401)"}, headers=admin)
    assert export.status_code == 200 and export.text.startswith("seq,time,principal")
    assert "POST /start" in export.text


def methods_by_path() -> dict[str, set[str]]:
    """Each route path's methods, as a client should be told them in Allow."""
    found: dict[str, set[str]] = {}
    for method, path in app_routes():
        found.setdefault(path, {"OPTIONS"}).add(method)
        if method == "GET":
            found[path].add("HEAD")
    return found


def allow_of(response: httpx.Response) -> set[str]:
    return {m.strip() for m in response.headers["allow"].split(",")}


async def test_head_answers_every_get_route_as_get_would_without_a_body(server) -> None:
    """HEAD needs what GET needs, and answers GET's status and headers with no body."""
    for method, path in app_routes():
        if method != "GET" or path == "/camera/frame":  # the frame: a new one each time
            continue
        url, needed = example_path(path), required_role("GET", path)
        if needed is not None:
            assert (await server.head(url)).status_code == 401, path
        if needed is not None and needed > Role.VIEWER:
            viewer = await server.head(url, headers=auth(server.tokens["viewer"]))
            assert viewer.status_code == 403, path
        headers = auth(server.tokens["admin"])
        got, head = await server.get(url, headers=headers), await server.head(url, headers=headers)
        assert head.status_code == got.status_code, (path, head.status_code, got.status_code)
        assert head.content == b"", path
        assert head.headers.get("content-type") == got.headers.get("content-type"), path


async def test_options_answers_each_paths_methods_in_allow(server) -> None:
    for path, methods in methods_by_path().items():
        url = example_path(path)
        answer = await server.options(url, headers=auth(server.tokens["admin"]))
        assert answer.status_code == 204, (path, answer.status_code, answer.text)
        assert allow_of(answer) == methods, path
    # OPTIONS needs no more than the least a path's methods need, and no less.
    assert (await server.options("/health")).status_code == 204
    assert (await server.options("/state")).status_code == 401
    viewer = auth(server.tokens["viewer"])
    assert allow_of(await server.options("/workpieces/demo", headers=viewer)) == {
        "GET",
        "HEAD",
        "OPTIONS",
        "PUT",
        "DELETE",
    }
    assert (await server.options("/tokens", headers=viewer)).status_code == 403
    unknown = await server.options("/no-such-path", headers=auth(server.tokens["admin"]))
    assert unknown.status_code == 404


async def test_a_method_a_path_does_not_answer_is_405_with_every_method_in_allow(server) -> None:
    admin = auth(server.tokens["admin"])
    refused = await server.patch("/workpieces", json={}, headers=admin)
    assert refused.status_code == 405
    assert allow_of(refused) == {"GET", "HEAD", "OPTIONS", "POST"}
    assert "PATCH" in refused.json()["detail"] and "/workpieces" in refused.json()["detail"]
    deleted = await server.delete("/state", headers=admin)
    assert deleted.status_code == 405 and allow_of(deleted) == {"GET", "HEAD", "OPTIONS"}


async def test_a_method_no_route_answers_needs_only_what_the_paths_own_methods_need(
    server,
) -> None:
    """The 405 tells what OPTIONS tells, so it needs no more (not ADMIN's 403)."""
    traced = await server.request("TRACE", "/health")  # /health is open
    assert traced.status_code == 405 and allow_of(traced) == {"GET", "HEAD", "OPTIONS"}
    viewer = auth(server.tokens["viewer"])
    deleted = await server.delete("/state", headers=viewer)
    assert deleted.status_code == 405 and allow_of(deleted) == {"GET", "HEAD", "OPTIONS"}
    anonymous = await server.delete("/state")
    assert anonymous.status_code == 401  # /state needs a viewer: so does learning its methods
    unknown = await server.request("TRACE", "/no-such-path", headers=viewer)
    assert unknown.status_code == 403  # a path the table does not know needs ADMIN


@contextlib.asynccontextmanager
async def served(settings: Settings, **uvicorn_overrides):
    """A client of the app on fakes with `settings`, served as `python -m server` serves it."""
    demo_stores(settings.data_path)
    cell = Cell(settings, devices=CellDevices(FakeRobot(50), FakeGlue(), FakeCamera()))
    async with (
        serve(cell, **uvicorn_overrides) as url,
        httpx.AsyncClient(base_url=url, timeout=10) as client,
    ):
        client.admin = admin_headers(settings.data_path)  # type: ignore[attr-defined]
        yield client


async def audited_addresses(client: httpx.AsyncClient, action: str) -> list[str]:
    async with asyncio.timeout(10):
        while True:
            rows = await client.get("/audit", params={"action": action}, headers=client.admin)
            addresses = [row["address"] for row in rows.json()["audit"]]
            if addresses:
                return addresses
            await asyncio.sleep(0.05)  # audit rows are written behind the answer


FORGED = ({"X-Forwarded-For": "10.1.2.3"}, {"Forwarded": "for=10.1.2.3"})


async def test_a_forwarded_address_cannot_walk_past_trusted_networks(fast_settings) -> None:
    settings = fast_settings.model_copy(update={"trusted_networks": ["10.0.0.0/8"]})
    async with served(settings) as client:
        for forged in FORGED:
            response = await client.get("/state", headers={**client.admin, **forged})
            assert response.status_code == 403, (forged, response.status_code)
            assert "127.0.0.1" in response.json()["detail"]
        url = str(client.base_url).replace("http", "ws") + "/ws"
        headers = {**client.admin, **FORGED[0]}
        async with websockets.connect(url, additional_headers=headers) as ws:
            with pytest.raises(websockets.ConnectionClosed) as closed:
                await asyncio.wait_for(ws.recv(), 5)
        assert closed.value.rcvd.code == 4401


async def test_the_audit_records_the_peer_not_the_address_a_client_wrote(server) -> None:
    await server.post("/start", headers={"X-Forwarded-For": "203.0.113.9"})  # refused: 401
    await server.post("/pause", headers={"Forwarded": "for=203.0.113.9"})
    server.admin = auth(server.tokens["admin"])
    assert await audited_addresses(server, "POST /start") == ["127.0.0.1"]
    assert await audited_addresses(server, "POST /pause") == ["127.0.0.1"]


async def test_a_trusted_proxy_is_believed_up_to_the_rightmost_hop_it_does_not_trust(
    fast_settings,
) -> None:
    settings = fast_settings.model_copy(
        update={
            "trusted_networks": ["10.0.0.0/8", "127.0.0.0/8"],
            "trusted_proxies": ["127.0.0.1", "192.0.2.0/24"],
        }
    )
    async with served(settings) as client:
        # The client wrote 10.1.1.1 itself; the proxies saw 203.0.113.5.
        chain = {"X-Forwarded-For": "10.1.1.1, 203.0.113.5, 192.0.2.7"}
        refused = await client.get("/state", headers={**client.admin, **chain})
        assert refused.status_code == 403 and "203.0.113.5" in refused.json()["detail"]
        chain = {"X-Forwarded-For": "203.0.113.5, 10.1.1.1, 192.0.2.7"}
        assert (await client.get("/state", headers={**client.admin, **chain})).status_code == 200
        await client.post("/start", headers={"X-Forwarded-For": "10.2.2.2"})
        assert await audited_addresses(client, "POST /start") == ["10.2.2.2"]
        # Only the configured header: a Forwarded the proxy passed through is the client's word.
        passed = {"Forwarded": "for=10.3.3.3", "X-Forwarded-For": "10.4.4.4"}
        await client.post("/pause", headers=passed)
        assert await audited_addresses(client, "POST /pause") == ["10.4.4.4"]


async def test_forwarded_addresses_stay_unbelieved_when_the_server_rewrites_them(
    fast_settings,
) -> None:
    """Served by uvicorn with its default proxy headers (loopback trusted), as a bare
    `uvicorn` command would: the rewritten address is refused, not believed."""
    settings = fast_settings.model_copy(update={"trusted_networks": ["10.0.0.0/8"]})
    async with served(settings, proxy_headers=True, forwarded_allow_ips="127.0.0.1") as client:
        forged = await client.get("/state", headers={**client.admin, **FORGED[0]})
        assert forged.status_code == 403, forged.status_code
        assert "X-Forwarded-For" in forged.json()["detail"]
    settings = fast_settings.model_copy(update={"trusted_networks": []})
    async with served(settings, proxy_headers=True, forwarded_allow_ips="127.0.0.1") as client:
        await client.post("/start", headers={"X-Forwarded-For": "10.9.9.9:4444"})
        assert "10.9.9.9" not in await audited_addresses(client, "POST /start")


def ws_url(client: httpx.AsyncClient) -> str:
    return str(client.base_url).replace("http", "ws") + "/ws"


async def closed_code(ws: websockets.ClientConnection) -> int | None:
    """The close code the server ends `ws` with (whatever it sent before); fails on a timeout."""
    async with asyncio.timeout(10):
        with pytest.raises(websockets.ConnectionClosed) as closed:
            while True:
                await ws.recv()
    return closed.value.rcvd.code if closed.value.rcvd else None


async def opened(ws: websockets.ClientConnection) -> bool:
    """Whether the server let `ws` in: it sends the snapshot first, else closes."""
    try:
        first = await asyncio.wait_for(ws.recv(), 10)
    except websockets.ConnectionClosed:
        return False
    assert '"type":"snapshot"' in str(first)
    return True


async def test_revoking_a_token_closes_its_live_views_and_voids_its_tickets(server) -> None:
    url, viewer = ws_url(server), auth(server.tokens["viewer"])
    used = (await server.post("/ws-ticket", headers=viewer)).json()["ticket"]
    unused = (await server.post("/ws-ticket", headers=viewer)).json()["ticket"]
    listed = (await server.get("/tokens", headers=auth(server.tokens["admin"]))).json()["tokens"]
    token_id = next(t["id"] for t in listed if t["name"] == "viewer")
    async with (
        websockets.connect(url, additional_headers=viewer) as by_token,
        websockets.connect(f"{url}?ticket={used}") as by_ticket,
        websockets.connect(url, additional_headers=auth(server.tokens["operator"])) as other,
    ):
        assert all([await opened(by_token), await opened(by_ticket), await opened(other)])
        revoked = await server.delete(f"/tokens/{token_id}", headers=auth(server.tokens["admin"]))
        assert revoked.status_code == 204
        assert await closed_code(by_token) == 4401
        assert await closed_code(by_ticket) == 4401
        await other.send('{"type": "ping"}')  # another token's view goes on
        async with asyncio.timeout(10):
            while '"pong"' not in str(await other.recv()):
                pass
    async with websockets.connect(f"{url}?ticket={unused}") as late:
        assert not await opened(late)
        assert late.close_code == 4401


async def test_one_token_cannot_take_every_live_view_slot(fast_settings) -> None:
    settings = fast_settings.model_copy(
        update={
            "max_broadcast_clients": 6,
            "max_broadcast_clients_per_token": 2,
            "broadcast_clients_reserved": 2,
        }
    )
    async with served(settings) as client, contextlib.AsyncExitStack() as stack:
        headers = {"admin": client.admin}
        for name in ("viewer", "viewer2", "operator", "maintenance"):
            role = name.rstrip("2")
            created = await client.post(
                "/tokens", json={"name": name, "role": role}, headers=client.admin
            )
            headers[name] = auth(created.json()["token"])

        async def connect(name: str) -> websockets.ClientConnection:
            return await stack.enter_async_context(
                websockets.connect(ws_url(client), additional_headers=headers[name])
            )

        first = await connect("viewer")
        assert await opened(first) and await opened(await connect("viewer"))
        third = await connect("viewer")
        assert not await opened(third)
        assert third.close_code == 1013 and "per_token" in (third.close_reason or "")
        assert await opened(await connect("viewer2")) and await opened(await connect("viewer2"))
        # Four of six slots are taken by viewers and operators; two are kept.
        operator = await connect("operator")
        assert not await opened(operator)
        assert operator.close_code == 1013 and "maintenance and admin" in operator.close_reason
        assert await opened(await connect("maintenance"))
        assert await opened(await connect("admin"))
        full = await connect("admin")
        assert not await opened(full) and full.close_code == 1013
        await first.close()
        async with asyncio.timeout(10):  # the server counts the slot free once it sees the close
            while not await opened(again := await connect("viewer")):
                await asyncio.sleep(0.05)
        assert again.close_code is None


def test_live_view_limits_default_to_ten_per_token_and_some_kept() -> None:
    settings = Settings()
    assert settings.max_broadcast_clients_per_token == 10
    assert 0 < settings.broadcast_clients_reserved < settings.max_broadcast_clients
