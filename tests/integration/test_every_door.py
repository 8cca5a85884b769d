"""Every command of the catalogue answers alike over HTTP, MQTT and OPC UA.

Each command is sent over each door that serves it (HTTP and signed MQTT serve every
command; OPC UA those the catalogue gives a method) three ways: by a token whose role
is too low (where the command needs more than a viewer), refused by the state (the
commands IDLE refuses), and accepted (the e-stop, then the reset that leaves ERROR).
Each door gives the same status (OPC UA's code for HTTP's), the same refusal text and
an audit row with the same outcome and detail. GET /state's `may` lists, for each
token, the commands the state and its role allow. A real cell with the simulators,
Debian's mosquitto and asyncua's Client.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from asyncua import Client, ua

from server.commands.catalogue import CATALOGUE, CommandSpec
from server.security.tokens import Role
from tests.integration.test_one_validation import (
    BASE,
    MqttRequester,
    _opc_call,
    cell_on_three_doors,
)
from tests.integration.test_opcua import endpoint, make_token
from tests.rig import WAIT_S, Rig
from tests.serving import free_port

# OPC UA's status for each HTTP status a command is answered with.
OPC_CODE = {
    202: ua.StatusCodes.Good,
    403: ua.StatusCodes.BadUserAccessDenied,
    409: ua.StatusCodes.BadInvalidState,
}
REFUSED_IN_IDLE = ("pause", "resume", "cancel", "reset")


def _label(status: int) -> str:
    return "accepted" if status < 400 else f"refused ({status})"


def _opc_label(code: int) -> str:
    return (
        "accepted"
        if code == ua.StatusCodes.Good
        else f"refused ({ua.StatusCode(ua.UInt32(code)).name})"
    )


async def _audit_row(rig: Rig, action: str) -> tuple[str, str]:
    """The newest audit row of `action`: its outcome and detail (its event's own id left
    out: each door's command is an event of its own)."""
    rows = (await rig.api.get("/audit", params={"limit": 1000})).json()["audit"]
    mine = [r for r in rows if r["action"] == action]
    assert mine, f"no audit row for {action}"
    newest = max(mine, key=lambda r: r["time"])
    return newest["outcome"], re.sub(r"^event \S+: ", "", newest["detail"])


class Doors:
    """One command sent over each door, each answer reduced to (status, text, audit row)."""

    def __init__(self, rig: Rig, mqtt: MqttRequester, opcs: dict[str, Client]) -> None:
        self.rig, self.mqtt, self.opcs = rig, mqtt, opcs

    async def http(self, spec: CommandSpec, token: str) -> tuple[int, str, tuple[str, str]]:
        answer = await self.rig.api.post(
            spec.path, headers={"Authorization": f"Bearer {token}"}, json=_body(spec)
        )
        body = answer.json()
        text = body.get("message") or body.get("detail")
        return answer.status_code, text, await _audit_row(self.rig, f"POST {spec.path}")

    async def over_mqtt(self, spec: CommandSpec, token: str) -> tuple[int, str, tuple[str, str]]:
        body = await self.mqtt.command(spec.name, token, _body(spec) or {})
        text = body.get("message") or body.get("detail")
        row = await _audit_row(self.rig, f"MQTT {BASE}/command/{spec.name}")
        return body["status"], text, row

    async def opc(self, spec: CommandSpec, role: str) -> tuple[int, str, tuple[str, str]]:
        assert spec.opcua is not None
        result = await _opc_call(self.opcs[role], spec.opcua.name)
        code = result.StatusCode.value
        message = result.OutputArguments[2].Value if result.OutputArguments else ""
        return code, message, await _audit_row(self.rig, f"OPC UA {spec.opcua.name}")

    async def compare(self, spec: CommandSpec, role: str, token: str, expected: int) -> str:
        """Send `spec` over every door as `role`; assert the answers agree; the text."""
        status, text, row = await self.http(spec, token)
        assert status == expected, (spec.name, status, text)
        assert row[0] == _label(status), (spec.name, row)
        m_status, m_text, m_row = await self.over_mqtt(spec, token)
        assert (m_status, m_row[0]) == (status, row[0]), (spec.name, m_status, m_row)
        if status != 202:  # a refusal: the same words, on the answer and the audit row
            assert m_text == text, (spec.name, m_text, text)
            assert m_row[1] == row[1], (spec.name, m_row, row)
        if spec.opcua is not None:
            code, o_text, o_row = await self.opc(spec, role)
            assert code == OPC_CODE[status], (spec.name, code)
            assert o_row[0] == _opc_label(code), (spec.name, o_row)
            if status != 202:
                assert o_text == text, (spec.name, o_text, text)
                assert o_row[1] == row[1], (spec.name, o_row, row)
        return text


def _body(spec: CommandSpec) -> dict[str, Any] | None:
    """A valid body for a command that must have one (jog); None for the rest."""
    return {"axis": "z", "distance_mm": 1.0} if spec.body_required else None


async def test_every_command_answers_alike_on_every_door(tmp_path: Path) -> None:
    port = free_port()
    async with cell_on_three_doors(tmp_path / "broker", tmp_path / "data", port) as (rig, mqtt):
        tokens = {role: await make_token(rig, role) for role in ("viewer", "maintenance")}
        opcs = {}
        for role, token in tokens.items():
            opcs[role] = Client(endpoint(port), timeout=WAIT_S)
            opcs[role].set_user("plc")
            opcs[role].set_password(token)
        async with opcs["viewer"], opcs["maintenance"]:
            doors = Doors(rig, mqtt, opcs)

            # GET /state's `may`: what the state allows that the caller's role allows.
            for role, token in tokens.items():
                state = (
                    await rig.api.get("/state", headers={"Authorization": f"Bearer {token}"})
                ).json()
                needs = {spec.name: spec.role for spec in CATALOGUE}
                assert state["may"] == [
                    name
                    for name in state["available_commands"]
                    if Role[role.upper()] >= needs[name]
                ], (role, state["may"])
                assert "estop" in state["may"]

            # Too low a role: every command that needs more than a viewer.
            for spec in CATALOGUE:
                if spec.role > Role.VIEWER:
                    text = await doors.compare(spec, "viewer", tokens["viewer"], 403)
                    assert spec.role.label in text, (spec.name, text)

            # Refused by the state: what IDLE does not allow.
            for spec in CATALOGUE:
                if spec.name in REFUSED_IN_IDLE:
                    await doors.compare(spec, "maintenance", tokens["maintenance"], 409)
            assert (await rig.state())["state"] == "IDLE"

            # Accepted: the e-stop (every role) and the reset that leaves ERROR, per door.
            estop, reset = (
                next(s for s in CATALOGUE if s.name == name) for name in ("estop", "reset")
            )
            for door in ("http", "mqtt", "opc"):
                for spec, role, state in (
                    (estop, "viewer", "ERROR"),
                    (reset, "maintenance", "IDLE"),
                ):
                    token = tokens[role]
                    if door == "http":
                        status, _, row = await doors.http(spec, token)
                    elif door == "mqtt":
                        status, _, row = await doors.over_mqtt(spec, token)
                    else:
                        status, _, row = await doors.opc(spec, role)
                        status = 202 if status == ua.StatusCodes.Good else status
                    assert (status, row[0]) == (202, "accepted"), (door, spec.name, row)
                    await rig.wait_state(state)
