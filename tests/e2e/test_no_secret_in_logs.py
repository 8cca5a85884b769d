"""No secret in any log, ever: `python -m server` at DEBUG with every transport on,
driven with every kind of secret a client hands it, then every log it wrote read back.

The scenario goes through each door a secret comes in by: HTTP with a bearer header
and with a token in the URL (`?token=`, `?access_token=`: refused, but the request
line is logged), a WebSocket ticket and a token in the /ws URL, an OPC UA session
signed in with a token as its password that calls a method, an MQTT command carrying
a token, the broker's password, and a webhook whose URL has a secret path and query.
Then every file under the data directory's `logs/`, every other `*.log` the server
wrote there, and its captured stdout and stderr must hold none of those secrets:
neither a whole token nor its secret part, nor the token's SHA-256 (the key a signed
MQTT command is checked with), the ticket, the broker password, the webhook's
HMAC key, its path or its query.
"""

from __future__ import annotations

import asyncio
import hashlib
import http.server
import json
import re
import secrets
import threading
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, ClassVar

import aiomqtt
import httpx
import websockets
from asyncua import Client, ua

from clients.client.mqtt_signing import sign_command
from server.line.broker import DEMO_PASSWORDS
from server.opcua.address_space import NAMESPACE_URI
from tests.mosquitto import WAIT_S, login_of, mosquitto
from tests.processes import server_process
from tests.serving import admin_headers, free_port

CELL = "cell-scan"
PREFIX = "glue"


class _Receiver(http.server.BaseHTTPRequestHandler):
    """A webhook receiver: answers 200 to every POST and keeps the path it was sent to."""

    paths: ClassVar[list[str]] = []

    def do_POST(self) -> None:
        self.rfile.read(int(self.headers.get("content-length") or 0))
        type(self).paths.append(self.path)
        self.send_response(200)
        self.send_header("content-length", "0")
        self.end_headers()

    def log_message(self, format: str, *args: Any) -> None:
        """Quiet: this is the test's receiver, not the server under test."""


@contextmanager
def webhook_receiver() -> Iterator[tuple[int, list[str]]]:
    handler = type("Receiver", (_Receiver,), {"paths": []})
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield server.server_address[1], handler.paths
    finally:
        server.shutdown()
        server.server_close()


async def _until(check: Any, what: str) -> Any:
    async with asyncio.timeout(WAIT_S):
        while not (found := await check()):
            await asyncio.sleep(0.1)
    assert found, what
    return found


async def _opcua_call(port: int, token: str, method: str) -> None:
    """An OPC UA session signed in with `token` as its password, calling `method`."""
    opc = Client(f"opc.tcp://127.0.0.1:{port}", timeout=WAIT_S)
    opc.set_user("plc")
    opc.set_password(token)
    async with opc:
        ns = await opc.get_namespace_index(NAMESPACE_URI)
        request = ua.CallMethodRequest()
        request.ObjectId = ua.NodeId.from_string(f"ns={ns};s={CELL}")
        request.MethodId = ua.NodeId.from_string(f"ns={ns};s={CELL}.{method}")
        request.InputArguments = []
        (result,) = await opc.uaclient.call([request])
        assert result.StatusCode.is_good(), result


async def test_no_secret_reaches_any_log_through_any_transport(tmp_path: Path) -> None:
    data = tmp_path / "data"
    stdout = tmp_path / "server-output.log"
    port, opcua_port = free_port(), free_port()
    hook_path = f"pathsecret{secrets.token_hex(12)}"
    hook_query = f"querysecret{secrets.token_hex(12)}"
    hook_key = f"hmac-key-{secrets.token_hex(16)}"
    with mosquitto(tmp_path / "broker") as broker, webhook_receiver() as (hook_port, posts):
        hook_url = f"http://127.0.0.1:{hook_port}/hooks/{hook_path}?auth={hook_query}"
        env = {
            "GLUE_APP_LOGGING_LEVEL": "DEBUG",
            "GLUE_APP_OPCUA_LOG_LEVEL": "DEBUG",  # asyncua's own lines too
            "GLUE_APP_CELL_ID": CELL,
            "GLUE_APP_SIMULATION_SPEED_FACTOR": "10",
            "GLUE_APP_OPCUA_ENDPOINT": f"opc.tcp://127.0.0.1:{opcua_port}",
            **broker.cell_environment,
            "GLUE_APP_MQTT_COMMANDS": "true",
            "GLUE_APP_WEBHOOKS": json.dumps(
                [{"name": "mes", "url": hook_url, "events": ["fault"], "secret": hook_key}]
            ),
            # the receiver is on 127.0.0.1, which the destination policy refuses unless allowed
            "GLUE_APP_WEBHOOK_ALLOWED_NETWORKS": '["127.0.0.0/8"]',
        }
        with server_process(port, data, env, log_path=stdout):
            admin = admin_headers(data)["Authorization"].removeprefix("Bearer ")
            url = f"http://127.0.0.1:{port}"
            async with httpx.AsyncClient(base_url=url, timeout=WAIT_S) as http:
                bearer = {"Authorization": f"Bearer {admin}"}
                made = await http.post(
                    "/tokens", json={"name": "plant", "role": "operator"}, headers=bearer
                )
                assert made.status_code == 201, made.text
                plant = made.json()["token"]
                assert (await http.get("/state", headers=bearer)).status_code == 200
                # A token in the URL is refused, but the request line was logged with it.
                assert (await http.get(f"/state?token={admin}")).status_code in (401, 422)
                assert (await http.get(f"/state?access_token={plant}")).status_code in (401, 422)

                ticket = (await http.post("/ws-ticket", headers=bearer)).json()["ticket"]
                async with websockets.connect(f"ws://127.0.0.1:{port}/ws?ticket={ticket}") as ws:
                    assert json.loads(await ws.recv())["type"] == "snapshot"
                try:  # refused (4401) or served: either way its URL reached uvicorn
                    async with websockets.connect(f"ws://127.0.0.1:{port}/ws?token={plant}") as ws:
                        await ws.recv()
                except websockets.ConnectionClosed:
                    pass

                # OPC UA: signed in with the plant token, the stop (every role may call it);
                # the stop's fault notice goes to the webhook with the secret path.
                await _opcua_call(opcua_port, plant, "EmergencyStop")
                await _until(lambda: _delivered(http, bearer), "the webhook was not delivered")
                assert posts and posts[0] == f"/hooks/{hook_path}?auth={hook_query}"

                # MQTT: a command with the plant token, answered and audited.
                topic = f"{PREFIX}/{CELL}/command/pause"
                async with aiomqtt.Client("127.0.0.1", broker.port, **login_of("operator")) as mqtt:
                    payload = json.dumps(sign_command(plant, topic, {})).encode()
                    await mqtt.publish(topic, payload, qos=1)
                await _until(lambda: _audited_mqtt(http, bearer), "no MQTT command was audited")

                assert (await http.post("/reset", headers=bearer)).status_code == 202

    logs = [*_server_logs(data), stdout]
    written = {path: path.read_text(encoding="utf-8", errors="replace") for path in logs}
    everything = "\n".join(written.values())
    secret_values = {
        "the admin token": admin,
        "the admin token's secret": admin.split("_", 2)[2],
        "the admin token's SHA-256": hashlib.sha256(admin.encode()).hexdigest(),
        "the plant token": plant,
        "the plant token's secret": plant.split("_", 2)[2],
        "the plant token's SHA-256": hashlib.sha256(plant.encode()).hexdigest(),
        "the WebSocket ticket": ticket,
        "the cell's broker password": DEMO_PASSWORDS["cell"],
        "an operator's broker password": DEMO_PASSWORDS["operator"],
        "the webhook's HMAC key": hook_key,
        "the webhook URL's path": hook_path,
        "the webhook URL's query": hook_query,
    }
    leaks = [
        f"{what} in {path.name}, from {_loggers_with(text, value)}: {_line_with(text, value)}"
        for what, value in secret_values.items()
        for path, text in written.items()
        if value in text
    ]
    assert not leaks, "\n".join(leaks)
    # The scenario reached the logs (at DEBUG, through each library), only without secrets.
    # asyncua's per-request line with its user (its call lines are the cell's call lane's:
    # server/opcua/call_lane.py answers calls itself)
    assert "Activate session request" in everything
    assert '"GET /state?... HTTP/1.1"' in everything  # uvicorn's access line, query dropped


async def _delivered(http: httpx.AsyncClient, bearer: dict[str, str]) -> bool:
    answer = await http.get("/webhooks/deliveries", headers=bearer)
    return any(d["outcome"] == "delivered" for d in answer.json()["webhook_deliveries"])


async def _audited_mqtt(http: httpx.AsyncClient, bearer: dict[str, str]) -> bool:
    audit = (await http.get("/audit", params={"limit": 1000}, headers=bearer)).json()["audit"]
    return any(row["action"].startswith("MQTT ") for row in audit)


def _server_logs(data: Path) -> list[Path]:
    """Every file under <data>/logs (rotated ones too) and every other *.log in <data>."""
    files = {p for p in (data / "logs").rglob("*") if p.is_file()}
    files |= {p for p in data.rglob("*.log*") if p.is_file()}
    assert files, f"the server wrote no log under {data}"
    return sorted(files)


def _loggers_with(text: str, value: str) -> list[str]:
    """The loggers whose lines carry `value` (the line's `[LEVEL] name:`)."""
    found = {re.search(r"\] ([\w.]+): ", line) for line in text.splitlines() if value in line}
    return sorted({match.group(1) for match in found if match} or {"?"})


def _line_with(text: str, value: str) -> str:
    return next(line for line in text.splitlines() if value in line)[:300]


def test_the_scan_would_see_a_secret(tmp_path: Path) -> None:
    """The scan's own check: a line with a secret is found (so a pass means something)."""
    (tmp_path / "logs").mkdir()
    secret = uuid.uuid4().hex
    (tmp_path / "logs" / "glue_cell.log").write_text(f"x\nGET /ws?ticket={secret}\n")
    logs = _server_logs(tmp_path)
    assert [_line_with(p.read_text(), secret) for p in logs] == [f"GET /ws?ticket={secret}"]
