"""The cell on OPC UA, through asyncua's own Client: a real server on loopback with the
robot and glue simulators, the same command path, roles and audit trail as HTTP."""

from __future__ import annotations

import asyncio
import json
import socket
import stat
import subprocess
import sys
from pathlib import Path
from typing import Any

import psutil
import pytest
from asyncua import Client, ua
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

from server.opcua.address_space import NAMESPACE_URI
from server.opcua.certificate import CERTIFICATE, DIRECTORY, KEY
from tests.processes import ROOT, environment
from tests.rig import WAIT_S, Rig, open_rig
from tests.serving import free_port

CELL = "cell-7"


def endpoint(port: int) -> str:
    return f"opc.tcp://127.0.0.1:{port}"


async def make_token(rig: Rig, role: str) -> str:
    created = await rig.api.post("/tokens", json={"name": f"plc-{role}", "role": role})
    assert created.status_code == 201, created.text
    return created.json()["token"]


def client(port: int, token: str | None = None) -> Client:
    opc = Client(endpoint(port), timeout=WAIT_S)
    if token is not None:
        opc.set_user("plc")
        opc.set_password(token)
    return opc


async def tag(opc: Client, path: str) -> Any:
    ns = await opc.get_namespace_index(NAMESPACE_URI)
    return await opc.get_node(f"ns={ns};s={CELL}.{path}").read_value()


async def call(opc: Client, method: str, *args: Any) -> ua.CallMethodResult:
    """A raw call, so a Bad answer's output arguments (the cell's message) can be read."""
    ns = await opc.get_namespace_index(NAMESPACE_URI)
    request = ua.CallMethodRequest()
    request.ObjectId = ua.NodeId.from_string(f"ns={ns};s={CELL}")
    request.MethodId = ua.NodeId.from_string(f"ns={ns};s={CELL}.{method}")
    request.InputArguments = [ua.Variant(a, ua.VariantType.String) for a in args]
    (result,) = await opc.uaclient.call([request])
    return result


class Recorder:
    """An OPC UA subscription handler: every value in the order it was notified."""

    def __init__(self) -> None:
        self.values: list[Any] = []

    def datachange_notification(self, node: Any, value: Any, data: Any) -> None:
        self.values.append(value)


async def until(condition: Any, timeout: float = WAIT_S) -> None:
    async with asyncio.timeout(timeout):
        while not await condition():
            await asyncio.sleep(0.05)


async def test_the_plant_reads_follows_and_commands_the_cell(tmp_path: Path) -> None:
    port = free_port()
    overrides = {"cell_id": CELL, "opcua_endpoint": endpoint(port), "opcua_admin_interval": 1}
    async with open_rig(tmp_path, **overrides) as rig:
        viewer, operator = await make_token(rig, "viewer"), await make_token(rig, "operator")

        async with client(port) as anonymous:
            # Browse: the cell's object holds Status, Admin, CellState and the methods.
            ns = await anonymous.get_namespace_index(NAMESPACE_URI)
            cell = anonymous.get_node(f"ns={ns};s={CELL}")
            names = {(await child.read_browse_name()).Name for child in await cell.get_children()}
            assert {
                "Status",
                "Admin",
                "CellState",
                "Start",
                "Pause",
                "Resume",
                "Cancel",
                "Reset",
                "EmergencyStop",
            } <= names
            # Read: PackML Idle, Production; no stop reason; CellState as /state says.
            assert await tag(anonymous, "Status.StateCurrent") == 4
            assert await tag(anonymous, "Status.UnitModeCurrent") == 1
            await anonymous.load_data_type_definitions()  # PackML's structures
            assert (await tag(anonymous, "Admin.StopReason")).Trigger is False
            document = json.loads(await tag(anonymous, "CellState"))
            assert document["state"] == "IDLE"
            assert set(document["devices"]) == {"robot", "glue", "camera"}
            await until(lambda: _positive(anonymous, "Admin.TimeInState.IDLE"))
            (processed,) = await tag(anonymous, "Admin.ProdProcessedCount")
            assert processed.Count == 0
            # Anonymous may read, never call.
            refused = await call(anonymous, "Start", "demo")
            assert refused.StatusCode.value == ua.StatusCodes.BadUserAccessDenied
            assert "authentication required" in refused.OutputArguments[2].Value

        async with client(port, viewer) as looking:
            refused = await call(looking, "Start", "demo")
            assert refused.StatusCode.value == ua.StatusCodes.BadUserAccessDenied
            assert "needs the operator role" in refused.OutputArguments[2].Value
        assert (await rig.state())["state"] == "IDLE"

        async with client(port, operator) as running:
            recorder = Recorder()
            subscription = await running.create_subscription(10, recorder)
            ns = await running.get_namespace_index(NAMESPACE_URI)
            await subscription.subscribe_data_change(
                running.get_node(f"ns={ns};s={CELL}.CellState"), queuesize=1000
            )
            # A state's own refusal: the cell's message, as HTTP's 409 gives it.
            refused = await call(running, "Resume")
            assert refused.StatusCode.value == ua.StatusCodes.BadInvalidState
            assert (
                refused.OutputArguments[2].Value
                == (await rig.api.post("/resume")).json()["message"]
            )
            accepted = await call(running, "Start", "demo")
            assert accepted.StatusCode.is_good(), accepted.OutputArguments[2].Value
            assert accepted.OutputArguments[0].Value is True
            assert accepted.OutputArguments[1].Value == "EXECUTING_TRAJECTORY"
            await rig.wait_state("EXECUTING_TRAJECTORY")
            await rig.wait_state("IDLE")
            await until(lambda: _seen_idle_again(recorder))
            states = _states(recorder)
            assert states == ["IDLE", "EXECUTING_TRAJECTORY", "IDLE"], states
            run = [json.loads(v) for v in recorder.values if json.loads(v)["waypoint"]]
            assert run and all(d["run_id"] == accepted.OutputArguments[3].Value for d in run)
            assert await tag(running, "Status.StateCurrent") == 17  # Complete: the part is done
            # A calibration's steps name it too: CellState took only progress with a waypoint.
            calibrating = await rig.api.post("/calibrate-robot")
            assert calibrating.status_code == 202, calibrating.text
            await rig.wait_state("IDLE")
            await until(lambda: _seen_idle_again(recorder))
            named = [
                json.loads(v)
                for v in recorder.values
                if json.loads(v)["state"] == "CALIBRATING_ROBOT" and json.loads(v)["operation"]
            ]
            assert named, [json.loads(v) for v in recorder.values][-5:]
            assert {d["run_id"] for d in named} == {calibrating.json()["run_id"]}

        async with client(port, viewer) as stopping:  # every role may stop, as on HTTP
            stopped = await call(stopping, "EmergencyStop")
            assert stopped.StatusCode.is_good(), stopped
            assert stopped.OutputArguments[1].Value == "ERROR"
            assert await tag(stopping, "Status.StateCurrent") == 9  # Aborted
            await stopping.load_data_type_definitions()
            reason = await tag(stopping, "Admin.StopReason")
            assert reason.Trigger is True
            assert reason.Message.startswith("EMERGENCY_STOP: ")
            assert json.loads(await tag(stopping, "CellState"))["state"] == "ERROR"

        audit = (await rig.api.get("/audit", params={"limit": 50})).json()["audit"]
        rows = [(r["principal"], r["action"], r["outcome"]) for r in audit]
        assert ("anonymous", "OPC UA Start", "refused (BadUserAccessDenied)") in rows
        assert any(
            p.startswith("plc-operator (operator") and a == "OPC UA Start" and o == "accepted"
            for p, a, o in rows
        ), rows
        assert any(
            p.startswith("plc-viewer (viewer") and a == "OPC UA EmergencyStop" and o == "accepted"
            for p, a, o in rows
        ), rows
        assert all(r["address"] == "127.0.0.1" for r in audit if r["action"].startswith("OPC"))


async def _positive(opc: Client, path: str) -> bool:
    return await tag(opc, path) > 0


def _states(recorder: Recorder) -> list[str]:
    """The cell's states as the subscription saw them, one entry per change of state."""
    states: list[str] = []
    for value in recorder.values:
        state = json.loads(value)["state"]
        if not states or states[-1] != state:
            states.append(state)
    return states


async def _seen_idle_again(recorder: Recorder) -> bool:
    return _states(recorder)[-1:] == ["IDLE"] and len(_states(recorder)) >= 3


async def test_basic256sha256_sign_and_encrypt_with_the_server_certificate(
    tmp_path: Path,
) -> None:
    port = free_port()
    data = tmp_path / "data"
    overrides = {"cell_id": CELL, "opcua_endpoint": endpoint(port), "opcua_allow_unsecured": False}
    async with open_rig(data, **overrides) as rig:
        operator = await make_token(rig, "operator")
        server_certificate = data / DIRECTORY / CERTIFICATE
        key = data / DIRECTORY / KEY
        assert stat.S_IMODE(key.stat().st_mode) == 0o600
        first = server_certificate.read_bytes()

        opc = client(port, operator)
        opc.application_uri = "urn:test:plant-client"
        certificate, private_key = await opc.setup_self_signed_certificate(
            tmp_path / "client" / "key.pem", tmp_path / "client" / "cert.der"
        )
        # The client trusts the server by its certificate, copied from the data directory.
        await opc.set_security(
            SecurityPolicyBasic256Sha256,
            str(certificate),
            str(private_key),
            server_certificate=str(server_certificate),
            mode=ua.MessageSecurityMode.SignAndEncrypt,
        )
        async with opc:
            assert await tag(opc, "Status.StateCurrent") == 4
            paused = await call(opc, "Pause")  # a call over the encrypted channel
            assert paused.StatusCode.value == ua.StatusCodes.BadInvalidState

            endpoints = await opc.get_endpoints()
            assert {e.SecurityPolicyUri for e in endpoints} == {SecurityPolicyBasic256Sha256.URI}
            assert {e.SecurityMode for e in endpoints} == {
                ua.MessageSecurityMode.Sign,
                ua.MessageSecurityMode.SignAndEncrypt,
            }
    async with open_rig(data, **overrides):  # a restart keeps the certificate clients trust
        assert server_certificate.read_bytes() == first


async def _answers_opcua(port: int) -> bool:
    opc = Client(endpoint(port), timeout=2)
    try:
        async with asyncio.timeout(5):
            await opc.connect_and_get_server_endpoints()
        return True
    except Exception:
        return False


def _listening_ports() -> set[int]:
    return {
        c.laddr.port
        for c in psutil.Process().net_connections(kind="tcp")
        if c.status == psutil.CONN_LISTEN
    }


@pytest.mark.parametrize("served", [False, True])
async def test_opcua_is_served_only_when_configured(tmp_path: Path, served: bool) -> None:
    port = free_port()
    before = _listening_ports()
    overrides = {"opcua_endpoint": endpoint(port)} if served else {}
    async with open_rig(tmp_path, **overrides) as rig:
        opened = _listening_ports() - before
        answering = [p for p in sorted(opened) if await _answers_opcua(p)]
        assert answering == ([port] if served else []), (opened, answering)
        assert rig.cell.settings.opcua_endpoint == (endpoint(port) if served else None)


def test_an_endpoint_in_use_stops_the_start_with_one_line(tmp_path: Path) -> None:
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        taken = holder.getsockname()[1]
        ran = subprocess.run(
            [
                sys.executable,
                "-m",
                "server",
                "--port",
                str(free_port()),
                "--data-dir",
                str(tmp_path),
            ],
            capture_output=True,
            text=True,
            env=environment({"GLUE_APP_OPCUA_ENDPOINT": endpoint(taken)}),
            cwd=ROOT,
            timeout=120,
        )
    output = ran.stdout + ran.stderr
    assert ran.returncode == 2, output
    assert f"cannot start: the OPC UA endpoint {endpoint(taken)} cannot be served" in output
    assert "Traceback" not in output


async def test_purge_is_a_method_for_the_maintenance_role(tmp_path: Path) -> None:
    """Purge over OPC UA: the catalogue's command, its role, refusal and audit row as
    POST /purge has them."""
    port = free_port()
    overrides = {"cell_id": CELL, "opcua_endpoint": endpoint(port), "purge_seconds": 0.2}
    async with open_rig(tmp_path, **overrides) as rig:
        operator = await make_token(rig, "operator")
        maintenance = await make_token(rig, "maintenance")
        async with client(port, operator) as running:
            ns = await running.get_namespace_index(NAMESPACE_URI)
            method = running.get_node(f"ns={ns};s={CELL}.Purge")
            assert (await method.read_browse_name()).Name == "Purge"
            executable = await method.read_attribute(ua.AttributeIds.UserExecutable)
            assert executable.Value.Value is False  # this session may not
            refused = await call(running, "Purge")
            assert refused.StatusCode.value == ua.StatusCodes.BadUserAccessDenied
            assert "needs the maintenance role" in refused.OutputArguments[2].Value
        assert not any(is_open for _, is_open in rig.glue.valve_log)  # nothing flowed
        async with client(port, maintenance) as fixing:
            ns = await fixing.get_namespace_index(NAMESPACE_URI)
            method = fixing.get_node(f"ns={ns};s={CELL}.Purge")
            executable = await method.read_attribute(ua.AttributeIds.UserExecutable)
            assert executable.Value.Value is True
            accepted = await call(fixing, "Purge")
            assert accepted.StatusCode.is_good(), accepted.OutputArguments[2].Value
            assert accepted.OutputArguments[0].Value is True
            assert accepted.OutputArguments[1].Value == "IDLE"

            async def purged() -> bool:
                counters = (await rig.api.get("/maintenance")).json()["counters"]
                return bool(counters["purges"] == 1)

            await until(purged)
            assert rig.glue.valve_open is False
            # Outside IDLE the cell refuses it: BadInvalidState with HTTP's 409 message.
            assert (await rig.api.post("/estop", json={"reason": "test"})).status_code == 202
            await rig.wait_state("ERROR")
            busy = await call(fixing, "Purge")
            assert busy.StatusCode.value == ua.StatusCodes.BadInvalidState
            assert busy.OutputArguments[2].Value == (await rig.api.post("/purge")).json()["message"]
        audit = (await rig.api.get("/audit", params={"limit": 100})).json()["audit"]
        rows = [(r["principal"], r["action"], r["outcome"]) for r in audit]
        assert any(
            p.startswith("plc-operator") and a == "OPC UA Purge" and o.startswith("refused")
            for p, a, o in rows
        ), rows
        assert any(
            p.startswith("plc-maintenance") and a == "OPC UA Purge" and o == "accepted"
            for p, a, o in rows
        ), rows
