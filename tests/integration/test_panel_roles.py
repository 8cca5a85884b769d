"""What a page learns of its user, and the words a stop leaves, against the real server.

GET /me names the token and its role, each command with the role it needs, what the
token may do in the current state and the pages its role may open. A stop made with a
token names the token in its reason ("emergency stop by line 3 HMI"); the address
stays in the audit row only.
"""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest

from tests.rig import Rig, open_rig


async def bearer(rig: Rig, name: str, role: str) -> dict[str, str]:
    created = await rig.api.post("/tokens", json={"name": name, "role": role})
    assert created.status_code == 201, created.text
    return {"Authorization": f"Bearer {created.json()['token']}"}


@pytest.mark.parametrize(
    ("role", "may_calibrate", "setup"),
    [
        ("viewer", False, False),
        ("operator", False, False),
        ("maintenance", True, True),
        ("admin", True, True),
    ],
)
async def test_me_says_who_is_signed_in_and_what_the_token_may_do(
    tmp_path: Path, role: str, may_calibrate: bool, setup: bool
) -> None:
    async with open_rig(tmp_path / "data") as rig:
        headers = await bearer(rig, f"{role} at line 3", role)
        answer = await rig.api.get("/me", headers=headers)
        assert answer.status_code == 200, answer.text
        me = answer.json()
        assert me["name"] == f"{role} at line 3"
        assert me["role"] == role
        needs = {c["name"]: c["role"] for c in me["commands"]}
        assert needs["reset"] == "maintenance" and needs["estop"] == "viewer"
        allowed = {c["name"] for c in me["commands"] if c["allowed"]}
        assert ("calibrate-robot" in allowed) is may_calibrate
        assert "estop" in allowed  # nobody is unable to stop the cell
        assert ("start" in me["may"]) is (role != "viewer")  # IDLE: start is available
        assert ("calibrate-robot" in me["may"]) is may_calibrate
        assert me["pages"] == {"setup": setup}
        # GET /state's `may` says the same for the same token.
        state = (await rig.api.get("/state", headers=headers)).json()
        assert state["may"] == me["may"]


async def test_a_stop_reason_names_the_token_and_the_audit_keeps_the_address(
    tmp_path: Path,
) -> None:
    async with open_rig(tmp_path / "data") as rig:
        headers = await bearer(rig, "line 3 HMI", "operator")
        stopped = await rig.api.post("/estop", headers=headers, json={"reason": "jam"})
        assert stopped.status_code == 202, stopped.text
        await rig.wait_state("ERROR")
        state = (await rig.api.get("/state")).json()
        reason = state["stop_reason"]
        assert reason["message"] == "emergency stop by line 3 HMI: jam", reason
        assert "127.0.0.1" not in reason["message"] and "127.0.0.1" not in reason["component"]
        # The operator is told whom to call: reset is available, its role does not allow it.
        me = (await rig.api.get("/me", headers=headers)).json()
        assert "reset" in state["available_commands"] and "reset" not in me["may"]
        audit = (await rig.api.get("/audit", params={"limit": 50})).json()
        rows = [r for r in audit["audit"] if r["action"] == "POST /estop"]
        assert rows and rows[0]["address"] == "127.0.0.1", rows
        assert "line 3 HMI" in rows[0]["principal"]


async def test_me_needs_a_token(tmp_path: Path) -> None:
    async with open_rig(tmp_path / "data") as rig:
        anonymous = httpx.AsyncClient(base_url=rig.api.base_url)
        async with anonymous:
            assert (await anonymous.get("/me")).status_code == 401
