"""Kill the server with SIGKILL the moment an audited action is answered: its audit row is
on disk all the same, for every kind of action (a command, the e-stop, a token created
or revoked, a settings change, a library edit).

An audit row written after the answer had left, without waiting for the disk, could be
lost with a crash: a token created just before it would work after the restart with no
row saying who created it, and an e-stop would be in /events with nobody pressing it.
"""

from __future__ import annotations

import signal
import sqlite3
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import httpx

from tests.processes import FAST_DEVICES, server_process
from tests.reliability.test_crash_safety import settled_state, wait_until
from tests.serving import admin_client, free_port

ROUNDS = 2  # bounded for CI: each round kills the server once per kind of action
OUTLINE = [[0.0, 0.0], [50.0, 0.0], [50.0, 30.0], [0.0, 30.0]]


@dataclass
class Trail:
    """What the test did and expects in the audit table: (action, a fragment of the detail)."""

    expected: list[tuple[str, str]] = field(default_factory=list)
    tokens: list[str] = field(default_factory=list)  # ids of tokens created, not yet revoked
    parts: list[str] = field(default_factory=list)  # library parts created, not yet deleted
    cycle: int = 0


Action = Callable[[httpx.Client, Trail], httpx.Response]


def command(client: httpx.Client, trail: Trail) -> httpx.Response:
    response = client.post("/home")
    assert response.status_code == 202, response.text
    trail.expected.append(("POST /home", f"event {response.json()['event_id']}"))
    return response


def estop(client: httpx.Client, trail: Trail) -> httpx.Response:
    response = client.post("/estop", json={"reason": f"audit test {trail.cycle}"})
    assert response.status_code == 202, response.text
    trail.expected.append(("POST /estop", f"event {response.json()['event_id']}"))
    return response


def create_token(client: httpx.Client, trail: Trail) -> httpx.Response:
    response = client.post("/tokens", json={"name": f"line {trail.cycle}", "role": "operator"})
    assert response.status_code == 201, response.text
    trail.tokens.append(response.json()["id"])
    trail.expected.append(("POST /tokens", f"created token {response.json()['id']}"))
    return response


def revoke_token(client: httpx.Client, trail: Trail) -> httpx.Response:
    token_id = trail.tokens.pop()
    response = client.delete(f"/tokens/{token_id}")
    assert response.status_code == 204, response.text
    trail.expected.append((f"DELETE /tokens/{token_id}", f"revoked token {token_id}"))
    return response


def change_settings(client: httpx.Client, trail: Trail) -> httpx.Response:
    response = client.patch("/settings", json={"error_state_timeout": 100 + trail.cycle})
    assert response.status_code == 200, response.text
    trail.expected.append(("PATCH /settings", f"-> {100 + trail.cycle}.0"))
    return response


def create_part(client: httpx.Client, trail: Trail) -> httpx.Response:
    response = client.post("/workpieces", json={"name": "bracket", "outline_mm": OUTLINE})
    assert response.status_code == 201, response.text
    trail.parts.append(response.json()["id"])
    trail.expected.append(("POST /workpieces", response.json()["id"]))
    return response


def replace_part(client: httpx.Client, trail: Trail) -> httpx.Response:
    part = trail.parts[-1]
    response = client.put(f"/workpieces/{part}", json={"name": "bracket 2", "outline_mm": OUTLINE})
    assert response.status_code == 200, response.text
    trail.expected.append((f"PUT /workpieces/{part}", part))
    return response


def delete_part(client: httpx.Client, trail: Trail) -> httpx.Response:
    part = trail.parts.pop()
    response = client.delete(f"/workpieces/{part}")
    assert response.status_code == 204, response.text
    trail.expected.append((f"DELETE /workpieces/{part}", part))
    return response


# In this order, so each revoke, replace and delete has its token or part from before.
ACTIONS: tuple[Action, ...] = (
    command,
    estop,
    create_token,
    revoke_token,
    change_settings,
    create_part,
    replace_part,
    delete_part,
)


def audit_rows(journal: Path) -> list[tuple[str, str, str]]:
    with sqlite3.connect(journal) as connection:
        return connection.execute("SELECT action, outcome, detail FROM audit").fetchall()


def event_ids(journal: Path) -> set[str]:
    with sqlite3.connect(journal) as connection:
        return {row[0] for row in connection.execute("SELECT id FROM events")}


def test_every_audited_action_keeps_its_row_through_a_kill_at_the_answer(tmp_path: Path) -> None:
    data = tmp_path / "cell"
    data.mkdir()
    journal = data / "journal.db"
    trail = Trail()
    for trail.cycle in range(ROUNDS * len(ACTIONS)):
        action = ACTIONS[trail.cycle % len(ACTIONS)]
        port = free_port()
        with server_process(port, data, FAST_DEVICES) as server:
            client = admin_client(port, data)
            if settled_state(client)["state"] == "ERROR":  # after an e-stop
                assert client.post("/reset").status_code == 202
            wait_until(lambda c=client: c.get("/state").json()["state"] == "IDLE", what="IDLE")
            response = action(client, trail)
            server.send_signal(signal.SIGKILL)  # the moment the answer is in
            server.wait(10)
            client.close()
        rows = audit_rows(journal)
        wanted, fragment = trail.expected[-1]
        found = [r for r in rows if r[0] == wanted and r[1] == "accepted" and fragment in r[2]]
        assert found, f"{action.__name__} answered {response.status_code}: no audit row {rows}"
        if action is estop:
            assert response.json()["event_id"] in event_ids(journal)
    # Every row asked for is there at the end too, none lost to a later crash.
    rows = audit_rows(journal)
    for wanted, fragment in trail.expected:
        assert any(r[0] == wanted and fragment in r[2] for r in rows), (wanted, fragment)
