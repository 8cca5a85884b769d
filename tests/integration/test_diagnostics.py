"""The diagnostic bundle, from a served cell (GET /diagnostics) and from its data
directory alone (`glue-server diagnose FILE`): what it holds, who may have it, and
that no token goes in."""

from __future__ import annotations

import asyncio
import io
import json
import stat
import subprocess
import sys
import tarfile
from pathlib import Path

from tests.integration.test_maintenance import seed
from tests.rig import open_rig


def unpacked(data: bytes) -> dict[str, bytes]:
    """The archive's files by their name under its one top directory."""
    with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as tar:
        members = [m for m in tar.getmembers() if m.isfile()]
        tops = {m.name.split("/", 1)[0] for m in members}
        assert len(tops) == 1, tops
        return {m.name.split("/", 1)[1]: tar.extractfile(m).read() for m in members}  # type: ignore[union-attr]


def run(command: list[str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(command, capture_output=True, text=True, timeout=120)


def tokens_of(data_path: Path, *more: str) -> list[str]:
    return [(data_path / "admin.token").read_text().strip(), *more]


async def test_a_served_cell_gives_its_bundle_to_maintenance_only(tmp_path) -> None:
    async with open_rig(tmp_path) as rig:
        await rig.start_spraying()
        assert (await rig.api.post("/estop", json={"reason": "bundle test"})).status_code == 202
        await rig.wait_state("ERROR")
        made = {}
        for role in ("operator", "maintenance"):
            answer = await rig.api.post("/tokens", json={"name": role, "role": role})
            made[role] = answer.json()["token"]
        refused = await rig.api.get(
            "/diagnostics", headers={"Authorization": f"Bearer {made['operator']}"}
        )
        assert refused.status_code == 403
        answer = await rig.api.get(
            "/diagnostics", headers={"Authorization": f"Bearer {made['maintenance']}"}
        )
        assert answer.status_code == 200
        assert answer.headers["content-type"] == "application/gzip"
        assert "attachment" in answer.headers["content-disposition"]
        files = unpacked(answer.content)
    assert {"README.txt", "version.json", "settings.json", "health.json"} <= set(files)
    assert {"faults.json", "transitions.json", "journal-check.txt"} <= set(files)
    assert json.loads(files["version.json"])["version"]
    health = json.loads(files["health.json"])
    assert health["devices"]["robot"]["connected"] is True  # the live /health
    fault = json.loads(files["faults.json"])[0]
    assert fault["code"] == "EMERGENCY_STOP" and fault["context"]["operation"] == "trajectory"
    transitions = json.loads(files["transitions.json"])
    assert transitions[0]["new_state"] == "ERROR"
    assert files["journal-check.txt"].startswith(b"ok: commits up to ")
    assert json.loads(files["settings.json"])["robot_ip"] == "127.0.0.1"
    maintenance = json.loads(files["maintenance.json"])
    assert maintenance["counters"]["valve_cycles"] > 0  # the run sprayed before the stop
    assert {i["name"] for i in maintenance["items"]} == {"clean nozzle", "service valve"}
    everything = b"".join(files.values())
    for token in tokens_of(tmp_path, *made.values()):
        assert token.encode() not in everything


async def test_the_command_line_bundle_needs_no_server(tmp_path) -> None:
    seed(tmp_path, {"parts": 250.0, "glue_ml": 120.0})  # the nozzle's cleaning overdue
    async with open_rig(tmp_path) as rig:
        await rig.start_spraying()
        assert (await rig.api.post("/estop")).status_code == 202
        await rig.wait_state("ERROR")
    out = tmp_path.parent / f"{tmp_path.name}-bundle.tar.gz"
    command = [sys.executable, "-m", "server", "diagnose", str(out), "--data-dir", str(tmp_path)]
    done = await asyncio.to_thread(run, command)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith(f"diagnostic bundle written: {out}")
    assert stat.S_IMODE(out.stat().st_mode) == 0o600
    files = unpacked(out.read_bytes())
    assert "not_asked" in json.loads(files["health.json"])
    assert json.loads(files["faults.json"])[0]["code"] == "EMERGENCY_STOP"
    assert files["journal-check.txt"].startswith(b"ok: ")
    # The maintenance state as GET /maintenance gave it, from the journal alone.
    maintenance = json.loads(files["maintenance.json"])
    assert maintenance["counters"]["parts"] == 250
    assert maintenance["counters"]["glue_ml"] >= 120.0  # and what the run dispensed, if any
    nozzle = next(i for i in maintenance["items"] if i["name"] == "clean nozzle")
    assert nozzle["status"] == "overdue" and nozzle["percent"] == 125.0, nozzle
    assert {"pot_life", "glue_level"} <= set(maintenance)
    assert "maintenance.json" in files["README.txt"].decode()
    everything = b"".join(files.values())
    for token in tokens_of(tmp_path):
        assert token.encode() not in everything
    again = await asyncio.to_thread(run, command)
    assert again.returncode == 1 and "exists" in again.stderr  # never overwrites
