"""https and wss served by `python -m server` itself.

With the HMI published on the plant network, plain http would carry every bearer
token and WebSocket ticket across it in clear. GLUE_APP_TLS_CERT_FILE and
GLUE_APP_TLS_KEY_FILE make the one HTTP port serve https and wss only. Each test
here uses a CA made for the test (tests/tls_pki.py) and the server as a process,
driven the way a plant would: gluectl and the Python client trusting that CA
(--ca-file), a /ws snapshot over wss with a ticket, and, refused, plain http, a
client that does not trust the CA, and TLS older than 1.2.
"""

from __future__ import annotations

import json
import socket
import ssl
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest
import websockets

from clients.client import AsyncCellClient, CellClient, Unreachable
from tests.processes import ROOT, _env, environment, server_process
from tests.serving import admin_headers, free_port
from tests.tls_pki import Pki, make_pki

SPRAY_DEMO = ("--no-contour-matching", "--workpiece", "demo")  # the commissioned part


@dataclass(frozen=True)
class TlsCell:
    url: str
    port: int
    data: Path
    pki: Pki

    @property
    def token(self) -> str:
        return (self.data / "admin.token").read_text().strip()


def tls_env(pki: Pki) -> dict[str, str]:
    return {
        "GLUE_APP_TLS_CERT_FILE": str(pki.cert_file),
        "GLUE_APP_TLS_KEY_FILE": str(pki.key_file),
    }


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TlsCell]:
    """`python -m server` on the simulated cell, serving https with the test CA's certificate."""
    pki = make_pki(tmp_path_factory.mktemp("pki"))
    data = tmp_path_factory.mktemp("cell")
    port = free_port()
    env = tls_env(pki) | {"GLUE_APP_SIMULATION_SPEED_FACTOR": "10"}
    with server_process(port, data, env, ca_file=pki.ca_file):
        cell = TlsCell(f"https://127.0.0.1:{port}", port, data, pki)
        # It answers /health while its devices come up (INITIALIZING), which takes longer
        # on a busy machine: the tests begin at IDLE. A bound, never a measure.
        trust = ssl.create_default_context(cafile=str(pki.ca_file))
        with httpx.Client(
            base_url=cell.url, verify=trust, headers=admin_headers(data), timeout=30
        ) as http:
            deadline = time.monotonic() + 120
            while http.get("/state").json()["state"] != "IDLE":
                assert time.monotonic() < deadline, "the cell did not come up IDLE"
                time.sleep(0.05)
        yield cell


def gluectl(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "clients.gluectl", *args],
        capture_output=True,
        text=True,
        env=environment({"COLUMNS": "200", **(env or {})}),
        cwd=ROOT,
        timeout=300,  # a hang guard, not a measure
    )


def test_gluectl_drives_a_cycle_over_https_with_the_ca_file(cell: TlsCell) -> None:
    where = ("--url", cell.url, "--data-dir", str(cell.data))
    started = gluectl(*where, "--ca-file", str(cell.pki.ca_file), "--json", "start", *SPRAY_DEMO)
    assert started.returncode == 0, started.stderr
    assert json.loads(started.stdout)["run_id"]
    # The CA file from the environment, as a script's unit file would set it.
    waited = gluectl(
        *where, "wait", "IDLE", "--timeout", "240", env={"GLUE_CELL_CA_FILE": str(cell.pki.ca_file)}
    )
    assert waited.returncode == 0, waited.stderr
    with CellClient(cell.url, cell.token, ca_file=cell.pki.ca_file) as client:
        latest = client.history(limit=1)
    assert (latest[0]["old_state"], latest[0]["new_state"]) == ("EXECUTING_TRAJECTORY", "IDLE")
    assert latest[0]["event"] == "OPERATION_COMPLETED", latest


async def test_the_python_client_reads_state_and_a_ws_snapshot_over_wss(cell: TlsCell) -> None:
    async with AsyncCellClient(cell.url, cell.token, ca_file=cell.pki.ca_file) as client:
        state = await client.state()
        assert state["state"] in {"IDLE", "EXECUTING_TRAJECTORY"}, state
        ticket = await client.ws_ticket()
        url = client.ws_url(ticket)
        assert url.startswith(f"wss://127.0.0.1:{cell.port}/ws?ticket="), url
        stream = client.messages(reconnect=False)
        async with stream:
            snapshot = await anext(stream)
    assert snapshot["type"] == "snapshot", snapshot


async def test_a_ws_snapshot_with_a_ticket_over_wss_with_websockets(cell: TlsCell) -> None:
    """The same with a bare WebSocket client, as a dashboard or bridge would open it."""
    trust = ssl.create_default_context(cafile=str(cell.pki.ca_file))
    headers = admin_headers(cell.data)
    async with httpx.AsyncClient(base_url=cell.url, verify=trust, headers=headers) as http:
        ticket = (await http.post("/ws-ticket")).json()["ticket"]
    async with websockets.connect(
        f"wss://127.0.0.1:{cell.port}/ws?ticket={ticket}", ssl=trust
    ) as socket_:
        snapshot = json.loads(await socket_.recv())
    assert snapshot["type"] == "snapshot", snapshot


def test_plain_http_to_the_tls_port_gets_no_answer(cell: TlsCell) -> None:
    with socket.create_connection(("127.0.0.1", cell.port), timeout=10) as plain:
        plain.sendall(b"GET /health HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
        answer = b""
        while chunk := plain.recv(4096):
            answer += chunk
    assert not answer.startswith(b"HTTP/"), answer[:200]
    with pytest.raises(httpx.TransportError):
        httpx.get(f"http://127.0.0.1:{cell.port}/health", timeout=10)
    # The server is still serving https after the refusal.
    trust = ssl.create_default_context(cafile=str(cell.pki.ca_file))
    assert httpx.get(f"{cell.url}/health", verify=trust, timeout=10).status_code == 200


def test_the_containers_health_check_asks_over_https(cell: TlsCell) -> None:
    """docker-compose.tls.yml's check: the server answers, whatever name its certificate
    has; plain http to the same port is unhealthy."""
    for url, code in ((f"{cell.url}/health", 0), (f"http://127.0.0.1:{cell.port}/health", 1)):
        ran = subprocess.run(
            [sys.executable, "-m", "server.cli.healthcheck", url],
            capture_output=True,
            text=True,
            env=environment(),
            cwd=ROOT,
            timeout=60,
        )
        assert ran.returncode == code, ran.stdout + ran.stderr


def test_a_client_without_the_ca_refuses_the_server(cell: TlsCell, tmp_path: Path) -> None:
    # The Python client with no CA file: the certificate is not one it trusts.
    with CellClient(cell.url, cell.token) as client, pytest.raises(Unreachable) as refused:
        client.state()
    assert "CERTIFICATE_VERIFY_FAILED" in str(refused.value)
    # A CA file of another CA: refused too.
    other = make_pki(tmp_path / "other")
    with (
        CellClient(cell.url, cell.token, ca_file=other.ca_file) as client,
        pytest.raises(Unreachable),
    ):
        client.state()
    # gluectl: exit 5 (unreachable), saying why; the token never sent.
    ran = gluectl("--url", cell.url, "--data-dir", str(cell.data), "state")
    assert ran.returncode == 5, ran.stderr
    assert "CERTIFICATE_VERIFY_FAILED" in ran.stderr
    assert cell.token not in ran.stderr + ran.stdout


def test_a_missing_ca_file_is_a_usage_error_naming_the_option(cell: TlsCell, tmp_path) -> None:
    ran = gluectl("--url", cell.url, "--ca-file", str(tmp_path / "nowhere.pem"), "state")
    assert ran.returncode == 2, ran.stderr
    assert "--ca-file" in ran.stderr and "nowhere.pem" in ran.stderr


@pytest.mark.filterwarnings("ignore:ssl.TLSVersion.TLSv1:DeprecationWarning")
def test_tls_older_than_1_2_is_refused(cell: TlsCell) -> None:
    old = ssl.create_default_context(cafile=str(cell.pki.ca_file))
    old.set_ciphers("DEFAULT:@SECLEVEL=0")  # let this client offer TLS 1.1 at all
    old.minimum_version = ssl.TLSVersion.TLSv1
    old.maximum_version = ssl.TLSVersion.TLSv1_1
    with (
        socket.create_connection(("127.0.0.1", cell.port), timeout=10) as raw,
        # The server's refusal: an alert, or (asyncio's TLS) the connection closed on the
        # hello. Not this client's own NO_PROTOCOLS_AVAILABLE: it did offer TLS 1.1.
        pytest.raises(ssl.SSLError, match=r"ALERT_PROTOCOL_VERSION|UNEXPECTED_EOF"),
        old.wrap_socket(raw, server_hostname="127.0.0.1"),
    ):
        pass
    modern = ssl.create_default_context(cafile=str(cell.pki.ca_file))
    modern.maximum_version = ssl.TLSVersion.TLSv1_2  # 1.2 itself is served
    with (
        socket.create_connection(("127.0.0.1", cell.port), timeout=10) as raw,
        modern.wrap_socket(raw, server_hostname="127.0.0.1") as tls,
    ):
        assert tls.version() == "TLSv1.2"


# --- refused at start ------------------------------------------------------------------


def start(tmp_path: Path, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    port = str(free_port())
    return subprocess.run(
        [sys.executable, "-m", "server", "--port", port, "--data-dir", str(tmp_path / "data")],
        capture_output=True,
        text=True,
        env=_env(env | {"GLUE_APP_COMMISSION_SIMULATED_CELL": "false"}),
        cwd=ROOT,
        timeout=120,  # a hang guard, not a measure
    )


def test_a_certificate_without_its_key_stops_the_start_naming_the_setting(tmp_path) -> None:
    pki = make_pki(tmp_path / "pki")
    for given, missing in (
        ({"GLUE_APP_TLS_CERT_FILE": str(pki.cert_file)}, "tls_key_file"),
        ({"GLUE_APP_TLS_KEY_FILE": str(pki.key_file)}, "tls_cert_file"),
    ):
        ran = start(tmp_path, given)
        assert ran.returncode == 2, ran.stderr
        (line,) = ran.stderr.splitlines()
        assert line.startswith("glue-server: cannot start: ") and missing in line, line


def test_unreadable_or_mismatched_files_stop_the_start_naming_the_setting(tmp_path) -> None:
    pki = make_pki(tmp_path / "pki")
    other = make_pki(tmp_path / "other")
    for env, named in (
        (tls_env(pki) | {"GLUE_APP_TLS_KEY_FILE": str(tmp_path / "no.key")}, "tls_key_file"),
        (tls_env(pki) | {"GLUE_APP_TLS_CERT_FILE": str(tmp_path / "no.pem")}, "tls_cert_file"),
        (tls_env(pki) | {"GLUE_APP_TLS_KEY_FILE": str(other.key_file)}, "tls_key_file"),
        (tls_env(pki) | {"GLUE_APP_TLS_CERT_FILE": str(pki.key_file)}, "tls_cert_file"),
    ):
        ran = start(tmp_path, env)
        assert ran.returncode == 2, ran.stderr
        refusals = [line for line in ran.stderr.splitlines() if "cannot start" in line]
        assert len(refusals) == 1 and named in refusals[0], ran.stderr
        assert "Traceback" not in ran.stderr
