"""OPC UA user tokens only when protected: an asyncua Client against the cell's real
endpoint, sending its password the way each channel allows, and the plain form a
hand-made client sends (EncryptionAlgorithm None) where nothing protects it.

The password is an API token; in plain text on a SecurityPolicy None channel (or a
Sign channel, which signs but does not encrypt) anyone on the network reads it, and
it is also a bearer token for HTTP. So it is accepted only encrypted with the server's
certificate (what the endpoints ask of a client, and what asyncua's Client does) or
inside a SignAndEncrypt channel; a plain one is refused when the session is activated,
with BadIdentityTokenRejected, and audited without the password.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

from server.opcua.address_space import NAMESPACE_URI
from server.opcua.certificate import CERTIFICATE, DIRECTORY
from tests.integration.test_opcua import CELL, call, endpoint, make_token, tag
from tests.rig import WAIT_S, open_rig
from tests.serving import free_port


class PlainPasswordClient(Client):
    """asyncua's Client, except that it sends the password as it is, never encrypted:
    what a careless or hostile client may do whatever the endpoint asks."""

    def _add_user_auth(
        self, params: ua.ActivateSessionParameters, username: str | None, password: str | None
    ) -> None:
        token = ua.UserNameIdentityToken()
        token.UserName = username
        token.PolicyId = self.server_policy(ua.UserTokenType.UserName).PolicyId
        token.Password = (password or "").encode("utf-8")
        token.EncryptionAlgorithm = None
        params.UserIdentityToken = token


async def _secured(
    opc: Client, tmp_path: Path, data: Path, mode: ua.MessageSecurityMode | None
) -> Client:
    """`opc` on a Basic256Sha256 channel in `mode` (None: the SecurityPolicy None channel)."""
    if mode is None:
        return opc
    opc.application_uri = "urn:test:plant-client"
    certificate, key = await opc.setup_self_signed_certificate(
        tmp_path / "client" / "key.pem", tmp_path / "client" / "cert.der"
    )
    await opc.set_security(
        SecurityPolicyBasic256Sha256,
        str(certificate),
        str(key),
        server_certificate=str(data / DIRECTORY / CERTIFICATE),
        mode=mode,
    )
    return opc


def _client(port: int, token: str, *, plain: bool) -> Client:
    kind = PlainPasswordClient if plain else Client
    opc = kind(endpoint(port), timeout=WAIT_S)
    opc.set_user("plc")
    opc.set_password(token)
    return opc


NONE, SIGN, SIGN_AND_ENCRYPT = (
    None,
    ua.MessageSecurityMode.Sign,
    ua.MessageSecurityMode.SignAndEncrypt,
)


@pytest.mark.parametrize(
    ("mode", "plain", "accepted"),
    [
        (NONE, True, False),  # the defect: a readable token activated a session
        (SIGN, True, False),  # signed, not encrypted: readable too
        (SIGN_AND_ENCRYPT, True, True),  # the channel encrypts it
        (NONE, False, True),  # encrypted with the server's certificate (asyncua's Client)
        (SIGN, False, True),
    ],
    ids=["none-plain", "sign-plain", "sign-and-encrypt-plain", "none-encrypted", "sign-encrypted"],
)
async def test_a_password_is_accepted_only_where_nobody_can_read_it(
    tmp_path: Path, mode: ua.MessageSecurityMode | None, plain: bool, accepted: bool
) -> None:
    port = free_port()
    data = tmp_path / "data"
    overrides: dict[str, Any] = {"cell_id": CELL, "opcua_endpoint": endpoint(port)}
    async with open_rig(data, **overrides) as rig:
        operator = await make_token(rig, "operator")
        opc = await _secured(_client(port, operator, plain=plain), tmp_path, data, mode)
        if accepted:
            async with opc:
                # The session reached the cell: the state's own refusal, not the gate's.
                paused = await call(opc, "Pause")
                assert paused.StatusCode.value == ua.StatusCodes.BadInvalidState, paused
            return
        with pytest.raises(ua.UaStatusCodeError) as refused:
            async with opc:
                await call(opc, "Start", "demo")  # never reached
        assert refused.value.code == ua.StatusCodes.BadIdentityTokenRejected, refused.value
        assert (await rig.state())["state"] == "IDLE"
        audit = (await rig.api.get("/audit", params={"limit": 100})).json()["audit"]
        rows = [r for r in audit if r["action"] == "OPC UA ActivateSession"]
        assert len(rows) == 1, audit
        (row,) = rows
        assert row["outcome"] == "refused (BadIdentityTokenRejected)"
        # Whose token crossed the network readable, so an admin knows what to revoke.
        assert row["principal"].startswith("plc-operator (operator"), row
        assert row["address"] == "127.0.0.1"
        assert "plain text" in row["detail"] and "revoke" in row["detail"], row
        assert operator not in str(audit)
        assert operator.split("_")[-1] not in str(audit)


async def _executable(opc: Client, method: str) -> tuple[bool, bool]:
    """(Executable, UserExecutable) of one of the cell's methods, as this session reads them."""
    ns = await opc.get_namespace_index(NAMESPACE_URI)
    node = opc.get_node(f"ns={ns};s={CELL}.{method}")
    executable = await node.read_attribute(ua.AttributeIds.Executable)
    user_executable = await node.read_attribute(ua.AttributeIds.UserExecutable)
    return executable.Value.Value, user_executable.Value.Value


async def test_anonymous_may_read_on_every_endpoint_but_never_call(tmp_path: Path) -> None:
    port = free_port()
    data = tmp_path / "data"
    async with open_rig(data, cell_id=CELL, opcua_endpoint=endpoint(port)) as rig:
        for mode in (NONE, SIGN, SIGN_AND_ENCRYPT):
            opc = await _secured(Client(endpoint(port), timeout=WAIT_S), tmp_path, data, mode)
            async with opc:
                assert await tag(opc, "Status.StateCurrent") == 4  # Idle
                # The methods say so before a call: executable, not by this session.
                assert await _executable(opc, "Start") == (True, False)
                assert await _executable(opc, "EmergencyStop") == (True, False)
                refused = await call(opc, "Start", "demo")
                assert refused.StatusCode.value == ua.StatusCodes.BadUserAccessDenied, mode
                stop = await call(opc, "EmergencyStop")
                assert stop.StatusCode.value == ua.StatusCodes.BadUserAccessDenied, mode
        assert (await rig.state())["state"] == "IDLE"


async def test_user_executable_follows_the_sessions_role(tmp_path: Path) -> None:
    """A viewer may stop the cell but not start it; an operator may do both."""
    port = free_port()
    async with open_rig(tmp_path / "data", cell_id=CELL, opcua_endpoint=endpoint(port)) as rig:
        for role, start, stop, reset in (
            ("viewer", False, True, False),
            ("operator", True, True, False),
            ("maintenance", True, True, True),
        ):
            async with _client(port, await make_token(rig, role), plain=False) as opc:
                assert await _executable(opc, "Start") == (True, start), role
                assert await _executable(opc, "EmergencyStop") == (True, stop), role
                assert await _executable(opc, "Reset") == (True, reset), role
