"""`glue-server backup` while the cell works, `glue-server restore` into a fresh directory.

One server run (commissioned, runs flowing) is shared by the tests of this
module: the backup is taken while runs are started and polled; a restore and a
second server are tried against it while it is live; then it is stopped and the
archive is restored and served again. The refusals are checked to change
nothing.
"""

from __future__ import annotations

import gzip
import io
import stat
import tarfile
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from subprocess import CompletedProcess

import httpx
import pytest

from tests.processes import run_module, server_process
from tests.serving import admin_client, admin_headers, free_port

FAST = {"GLUE_APP_SIMULATION_SPEED_FACTOR": "10"}


@dataclass
class Flow:
    """Starts a run whenever the cell is IDLE, and reads /state, until stopped."""

    client: httpx.Client
    started: list[int] = field(default_factory=list)  # run ids answered 202
    requests: int = 0
    stop: threading.Event = field(default_factory=threading.Event)

    def run(self) -> None:
        while not self.stop.is_set():
            state = self.client.get("/state").json()["state"]
            self.requests += 1
            if state == "IDLE":
                answer = self.client.post("/start")
                self.requests += 1
                if answer.status_code == 202:
                    self.started.append(answer.json()["event_id"])
            time.sleep(0.02)

    def wait_for(self, condition: object, what: str, limit: float = 120) -> None:
        deadline = time.monotonic() + limit
        while not callable(condition) or not condition():
            assert time.monotonic() < deadline, f"no {what}"
            time.sleep(0.05)


@dataclass
class BackedUp:
    data: Path
    archive: Path
    backup: CompletedProcess[str]
    restore_while_live: CompletedProcess[str]
    restore_while_live_unforced: CompletedProcess[str]
    second_server: CompletedProcess[str]
    files_while_live: dict[str, bytes]  # the data directory's calibration, library, tokens
    finished_before_backup: set[int]  # run ids the journal had ended before the backup began
    workpieces: list[str]
    token_names: list[str]
    calibration: dict


def contents(root: Path) -> dict[str, tuple[int, bytes]]:
    """Every file and directory under `root`: mode and bytes (b"" for a directory)."""
    found: dict[str, tuple[int, bytes]] = {}
    for path in sorted(root.rglob("*")):
        mode = path.lstat().st_mode
        found[path.relative_to(root).as_posix()] = (
            mode,
            b"" if stat.S_ISDIR(mode) else path.read_bytes(),
        )
    return found


def wait_idle(client: httpx.Client) -> None:
    deadline = time.monotonic() + 120
    while client.get("/state").json()["state"] != "IDLE":
        assert time.monotonic() < deadline, "the cell did not come up IDLE"
        time.sleep(0.05)


@pytest.fixture(scope="module")
def backed_up(tmp_path_factory: pytest.TempPathFactory) -> Iterator[BackedUp]:
    root = tmp_path_factory.mktemp("backup")
    data = root / "data"
    archive = root / "cell.tar.gz"
    port = free_port()
    with server_process(port, data, FAST, log_path=root / "server.log"):
        client = admin_client(port, data)
        wait_idle(client)  # commissioned: both calibrations and the demo part
        assert client.post("/tokens", json={"name": "line-3", "role": "viewer"}).status_code == 201
        flow = Flow(httpx.Client(base_url=client.base_url, headers=client.headers, timeout=30))
        runner = threading.Thread(target=flow.run, daemon=True)
        runner.start()
        try:
            flow.wait_for(lambda: len(flow.started) >= 2, "second run started")
            operations = client.get("/operations", params={"limit": 1000}).json()["operations"]
            finished = {op["run_id"] for op in operations if op["ended_at"] is not None}
            assert finished, operations
            before = flow.requests
            backup = run_module("server", "backup", str(archive), "--data-dir", str(data))
            flow.wait_for(lambda: flow.requests > before + 2, "command after the backup")
            restore_live = run_module(
                "server", "restore", str(archive), "--data-dir", str(data), "--force"
            )
            unforced = run_module("server", "restore", str(archive), "--data-dir", str(data))
            second = run_module("server", "--port", str(free_port()), "--data-dir", str(data))
            files = {
                p.relative_to(data).as_posix(): p.read_bytes()
                for p in sorted(data.rglob("*"))
                if p.is_file() and p.parts[len(data.parts)] in ("calibration", "workpieces")
            }
            files["tokens.json"] = (data / "tokens.json").read_bytes()
        finally:
            flow.stop.set()
            runner.join(60)
        wait_idle(client)
        workpieces = sorted(w["id"] for w in client.get("/workpieces").json()["workpieces"])
        tokens = sorted(t["name"] for t in client.get("/tokens").json()["tokens"])
        calibration = client.get("/calibration").json()
    yield BackedUp(
        data,
        archive,
        backup,
        restore_live,
        unforced,
        second,
        files,
        finished,
        workpieces,
        tokens,
        calibration,
    )


def test_backup_while_runs_flow_restores_into_a_fresh_directory_and_serves(
    backed_up: BackedUp, tmp_path: Path
) -> None:
    assert backed_up.backup.returncode == 0, backed_up.backup.stderr
    assert "backup written" in backed_up.backup.stdout
    assert stat.S_IMODE(backed_up.archive.stat().st_mode) == 0o600  # it holds admin.token
    fresh = tmp_path / "fresh"
    restored = run_module("server", "restore", str(backed_up.archive), "--data-dir", str(fresh))
    assert restored.returncode == 0, restored.stderr
    for name, (mode, _) in contents(fresh).items():
        expected = 0o700 if stat.S_ISDIR(mode) else 0o600
        assert stat.S_IMODE(mode) == expected, name
    checked = run_module("server.storage.journal.check", str(fresh / "journal.db"))
    assert checked.returncode == 0, checked.stdout
    assert checked.stdout.startswith("ok: commits up to ")
    assert not (fresh / "logs").exists()  # logs are not state
    port = free_port()
    with server_process(port, fresh, FAST, log_path=tmp_path / "server.log"):
        client = httpx.Client(
            base_url=f"http://127.0.0.1:{port}", headers=admin_headers(fresh), timeout=30
        )
        health = client.get("/health").json()
        assert health["journal"].get("damage") in (None, []), health["journal"]
        operations = client.get("/operations", params={"limit": 1000}).json()["operations"]
        assert backed_up.finished_before_backup <= {op["run_id"] for op in operations}
        assert sorted(w["id"] for w in client.get("/workpieces").json()["workpieces"]) == (
            backed_up.workpieces
        )
        assert sorted(t["name"] for t in client.get("/tokens").json()["tokens"]) == (
            backed_up.token_names
        )
        calibration = client.get("/calibration").json()
        assert calibration == backed_up.calibration
    # What the server keeps in files came back byte for byte (the server wrote none after).
    for name, content in backed_up.files_while_live.items():
        assert (fresh / name).read_bytes() == content, name


def test_restore_and_a_second_server_are_refused_while_the_server_runs(
    backed_up: BackedUp,
) -> None:
    refused = backed_up.restore_while_live
    assert refused.returncode == 1
    assert "refused" in refused.stderr and "stop the server first" in refused.stderr
    assert "server pid" in refused.stderr
    assert not any(p.name.startswith("before-restore-") for p in backed_up.data.iterdir())
    second = backed_up.second_server
    assert second.returncode == 2
    assert "cannot start" in second.stderr and "in use" in second.stderr
    assert "Traceback" not in refused.stderr + second.stderr
    # Without --force too, the first thing said is that a server holds it: forcing
    # would not help, stopping the server would.
    unforced = backed_up.restore_while_live_unforced
    assert unforced.returncode == 1
    assert "in use" in unforced.stderr and "stop the server first" in unforced.stderr
    assert "--force" not in unforced.stderr, unforced.stderr


def test_restore_into_a_data_directory_in_use_needs_force_and_moves_it_aside(
    backed_up: BackedUp, tmp_path: Path
) -> None:
    target = tmp_path / "data"
    first = run_module("server", "restore", str(backed_up.archive), "--data-dir", str(target))
    assert first.returncode == 0, first.stderr
    (target / "workpieces" / "note.txt").write_text("kept")
    before = contents(target)
    refused = run_module("server", "restore", str(backed_up.archive), "--data-dir", str(target))
    assert refused.returncode == 1 and "--force" in refused.stderr, refused.stderr
    assert contents(target) == before
    forced = run_module(
        "server", "restore", str(backed_up.archive), "--data-dir", str(target), "--force"
    )
    assert forced.returncode == 0, forced.stderr
    (aside,) = [p for p in target.iterdir() if p.name.startswith("before-restore-")]
    assert (aside / "workpieces" / "note.txt").read_text() == "kept"
    assert not (target / "workpieces" / "note.txt").exists()


def rewritten(archive: Path, change: str) -> bytes:
    """The archive with one member changed, its manifest left as it was (or, for
    "last-commit", updated to match: a consistent archive whose journal does not check)."""
    import hashlib
    import json

    with tarfile.open(archive, "r:gz") as tar:
        members = [(m, tar.extractfile(m).read()) for m in tar.getmembers()]  # type: ignore[union-attr]
    manifest = json.loads(members[0][1])
    out = io.BytesIO()
    with tarfile.open(fileobj=out, mode="w:gz") as tar:
        changed = []
        for member, content in members[1:]:
            if change == "tokens" and member.name == "data/tokens.json":
                content = content.replace(b'"viewer"', b'"admin" ')
            if change == "last-commit" and member.name == "data/journal.db.last-commit":
                head = json.loads(content)
                head["seq"] += 5
                content = json.dumps(head).encode().ljust(len(content))
                name = member.name.removeprefix("data/")
                manifest["files"][name]["sha256"] = hashlib.sha256(content).hexdigest()
            member.size = len(content)
            changed.append((member, content))
        document = json.dumps(manifest).encode()
        info = tarfile.TarInfo("manifest.json")
        info.size = len(document)
        tar.addfile(info, io.BytesIO(document))
        for member, content in changed:
            tar.addfile(member, io.BytesIO(content))
    return out.getvalue()


@pytest.mark.parametrize("damage", ["truncated", "flipped", "tokens", "last-commit", "not-ours"])
@pytest.mark.parametrize("into", ["absent", "in use, forced"])
def test_a_damaged_archive_is_refused_and_nothing_changes(
    backed_up: BackedUp, tmp_path: Path, damage: str, into: str
) -> None:
    original = backed_up.archive.read_bytes()
    corrupt = tmp_path / "corrupt.tar.gz"
    if damage == "truncated":
        corrupt.write_bytes(original[: len(original) * 2 // 3])
    elif damage == "flipped":
        middle = len(original) // 2
        corrupt.write_bytes(
            original[:middle] + bytes([original[middle] ^ 0xFF]) + original[middle + 1 :]
        )
    elif damage == "not-ours":
        corrupt.write_bytes(gzip.compress(b"not a tar archive at all" * 100))
    else:
        corrupt.write_bytes(rewritten(backed_up.archive, damage))
    target = tmp_path / "data"
    if into == "in use, forced":
        first = run_module("server", "restore", str(backed_up.archive), "--data-dir", str(target))
        assert first.returncode == 0, first.stderr
        (target / "journal.db").write_bytes(b"the cell's own journal")  # must survive as it is
    before = contents(target) if target.exists() else None
    args = ["server", "restore", str(corrupt), "--data-dir", str(target)]
    refused = run_module(*args, *(["--force"] if into == "in use, forced" else []))
    assert refused.returncode == 1, refused.stdout + refused.stderr
    assert "refused" in refused.stderr and "Traceback" not in refused.stderr
    assert (contents(target) if target.exists() else None) == before
