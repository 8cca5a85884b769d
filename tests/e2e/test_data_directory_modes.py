"""Files only for the cell: everything `glue-server` keeps is its user's alone."""

from __future__ import annotations

import os
import stat
import time
from pathlib import Path

from tests.processes import server_process
from tests.serving import admin_client, free_port

LOG_MODE = 0o640  # group may read the log (never a secret in it); nobody else
FILE_MODE = 0o600
DIRECTORY_MODE = 0o700


def modes_under(root: Path) -> dict[str, int]:
    """Every entry under `root` (itself as "."), with its permission bits and file type."""
    found = {".": root.stat().st_mode}
    for path in root.rglob("*"):
        try:
            found[str(path.relative_to(root))] = path.lstat().st_mode
        except FileNotFoundError:  # a temporary file renamed meanwhile
            continue
    return found


def expected_mode(name: str, mode: int) -> int:
    if stat.S_ISDIR(mode):
        return DIRECTORY_MODE
    return LOG_MODE if name.startswith("logs/glue_cell.log") else FILE_MODE


def test_every_file_and_directory_the_server_keeps_is_private(tmp_path) -> None:
    data = tmp_path / "data"
    data.mkdir(mode=0o755)  # as an installer might leave it
    data.chmod(0o755)
    port = free_port()
    with server_process(port, data, {"GLUE_APP_SIMULATION_SPEED_FACTOR": "10"}):
        client = admin_client(port, data)
        deadline = time.monotonic() + 60
        while client.get("/state").json()["state"] != "IDLE":  # commissioned: calibrated, a part
            assert time.monotonic() < deadline
            time.sleep(0.05)
        assert client.post("/tokens", json={"name": "hmi", "role": "viewer"}).status_code == 201
        while not (data / "state.json").exists():
            assert time.monotonic() < deadline
            time.sleep(0.05)
        modes = modes_under(data)
        log_text = (data / "logs" / "glue_cell.log").read_text(encoding="utf-8")
    kept = set(modes)
    for name in (
        ".",
        "journal.db",
        "journal.db-wal",
        "journal.db-shm",
        "state.json",
        "tokens.json",
        "admin.token",
        "logs",
        "logs/glue_cell.log",
        "calibration",
        "calibration/robot.json",
        "workpieces",
    ):
        assert name in kept, f"{name} not written: {sorted(kept)}"
    assert any(name.startswith("workpieces/") for name in kept)
    wrong = {
        name: f"{stat.S_IMODE(mode):o}"
        for name, mode in modes.items()
        if stat.S_IMODE(mode) != expected_mode(name, mode)
    }
    assert wrong == {}, wrong
    assert "tightened" in log_text and "755" in log_text  # the data directory, said so


def test_nothing_else_on_the_machine_can_read_the_journal_even_with_a_loose_umask(
    tmp_path,
) -> None:
    """The modes are the server's own, not the umask's: a umask of 0 changes nothing."""
    data = tmp_path / "data"
    data.mkdir()
    previous = os.umask(0)  # inherited by the server process
    try:
        with server_process(free_port(), data):
            pass
    finally:
        os.umask(previous)
    modes = {name: stat.S_IMODE(mode) for name, mode in modes_under(data).items()}
    assert modes["."] == DIRECTORY_MODE and modes["journal.db"] == FILE_MODE, modes
    assert modes["logs"] == DIRECTORY_MODE and modes["logs/glue_cell.log"] == LOG_MODE, modes
