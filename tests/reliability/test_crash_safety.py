"""Kill the server with SIGKILL at random moments: nothing acknowledged is lost,
the journal stays intact, and a cell that died mid-operation comes back in
ERROR with the reason and the glue valve closed, never resuming by itself.

The simulators run as their own processes and outlive every server crash, as
real devices would.
"""

from __future__ import annotations

import asyncio
import contextlib
import random
import signal
import sqlite3
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from server.drivers.glue_modbus import ModbusGlueDispenser
from tests.processes import FAST_DEVICES, has_ended, server_process, simulator
from tests.serving import admin_client, free_port

KILLS = 6  # bounded for CI; each cycle starts, runs and kills a real server
SPRAY_DEMO = {"contour_matching": False, "workpiece_id": "demo"}


# A hang guard, never a measure: a restarted server's cell comes up in seconds alone, and
# many times slower beside the suite's other workers on the same cores (make test).
WAIT_S = 120.0


def wait_until(predicate, timeout: float = WAIT_S, what: str = "condition"):
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.02)


def settled_state(client: httpx.Client) -> dict:
    """The state once the server has left INITIALIZING."""
    return wait_until(
        lambda: (s := client.get("/state").json())["state"] != "INITIALIZING" and s,
        what="the cell to leave INITIALIZING",
    )


def unfinished_operations(journal: Path) -> int:
    if not journal.exists():
        return 0
    with sqlite3.connect(journal) as connection:
        return connection.execute(
            "SELECT COUNT(*) FROM operations WHERE ended_at IS NULL"
        ).fetchone()[0]


async def valve_reads_closed(port: int) -> bool:
    glue = ModbusGlueDispenser.tcp("127.0.0.1", port, timeout=2, poll_interval=3600)
    await glue.connect()
    try:
        return (await glue.read_status()).valve_open is False
    finally:
        await glue.close()


def test_sigkill_at_random_moments(tmp_path: Path) -> None:
    rng = random.Random(20261122)
    data = tmp_path / "cell"
    data.mkdir()
    acknowledged: set[str] = set()
    died_mid_operation = 0
    with (
        simulator("server.drivers.sim.robot_sim", "--speed-factor", "4") as robot,
        simulator("server.drivers.sim.glue_sim") as glue,
    ):
        env = {
            "ROBOT_IP": "127.0.0.1",
            "GLUE_APP_ROBOT_PORT": str(robot.port),
            "GLUE_CONTROLLER_PORT": f"tcp://127.0.0.1:{glue.port}",
        }
        for cycle in range(KILLS + 1):
            unfinished = unfinished_operations(data / "journal.db")
            port = free_port()
            with server_process(port, data, env) as server:
                client = admin_client(port, data)
                state = settled_state(client)
                journal = data / "journal.db"
                # After every crash: everything acknowledged is on disk, the file is sound.
                with sqlite3.connect(journal) as connection:
                    assert connection.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
                    stored = {row[0] for row in connection.execute("SELECT id FROM events")}
                assert acknowledged <= stored, f"lost: {sorted(acknowledged - stored)}"
                # A kill is no damage: the commit chain found nothing missing or rewritten.
                assert client.get("/health").json()["journal"]["damage"] == []
                if cycle == KILLS:
                    break
                # Died mid-operation (an operation never closed in the journal):
                # ERROR with the reason, valve closed; otherwise a normal start to IDLE.
                if unfinished:
                    died_mid_operation += 1
                    assert state["state"] == "ERROR", state
                    reason = state["stop_reason"]
                    assert reason["code"] == "INTERRUPTED"
                    assert reason["message"].startswith("interrupted during ")
                    assert asyncio.run(valve_reads_closed(glue.port))
                else:
                    assert state["state"] in ("IDLE", "INITIALIZING"), state
                if state["state"] == "ERROR":
                    reset = client.post("/reset")
                    acknowledged.add(reset.json()["event_id"])
                    assert reset.status_code == 202, reset.text
                wait_until(lambda c=client: c.get("/state").json()["state"] == "IDLE", what="IDLE")
                # Work, acknowledged step by step, then a kill at a random moment.
                for _ in range(rng.randint(1, 3)):
                    for command, body in (("start", SPRAY_DEMO), ("pause", None), ("resume", None)):
                        response = client.post(f"/{command}", json=body)
                        assert response.status_code in (202, 409), response.text
                        acknowledged.add(response.json()["event_id"])
                        time.sleep(rng.uniform(0.0, 0.3))
                time.sleep(rng.uniform(0.0, 1.0))
                server.send_signal(signal.SIGKILL)
                server.wait(10)
    assert died_mid_operation >= 1, "no kill landed during an operation; the test proved little"


# The image process's tests read the process table from /proc: Linux, as CI is.
linux_only = pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="reads /proc")


@contextlib.contextmanager
def idle_server(tmp_path: Path) -> Iterator[tuple[subprocess.Popen[str], Path]]:
    """`python -m server` on a fresh data directory, once its cell is IDLE; and that directory."""
    data = tmp_path / "cell"
    data.mkdir()
    port = free_port()
    with server_process(port, data, FAST_DEVICES) as server:
        client = admin_client(port, data)
        wait_until(lambda: client.get("/state").json()["state"] == "IDLE", what="IDLE")
        yield server, data


def _children(pid: int) -> list[int]:
    path = Path(f"/proc/{pid}/task/{pid}/children")
    return [int(p) for p in path.read_text().split()] if path.exists() else []


def _shared_blocks(pid: int) -> set[str]:
    """The shared memory blocks a process has mapped (the image process's frames)."""
    maps = Path(f"/proc/{pid}/maps").read_text().splitlines()
    return {line.split()[-1] for line in maps if "/dev/shm/psm_" in line}


@linux_only
def test_the_image_process_ends_with_a_killed_server(tmp_path: Path) -> None:
    """A server killed outright leaves no image process behind, nor its frames' memory.

    On ad6615e (the first cut) the child waited for work forever: it holds both ends of
    its call queue, so the server's death never reached it.
    """
    with idle_server(tmp_path) as (server, _):
        # The simulated camera's frames are drawn in the image process: it is running.
        workers = [
            pid
            for pid in _children(server.pid)
            if "spawn_main" in Path(f"/proc/{pid}/cmdline").read_text()
        ]
        assert workers, "no image process under the server"
        blocks = set().union(*(_shared_blocks(pid) for pid in workers))
        assert blocks, "the image process has no frame memory mapped"
        server.send_signal(signal.SIGKILL)
        server.wait(10)
        wait_until(lambda: all(has_ended(pid) for pid in workers), what="the child to end")
        wait_until(lambda: not any(Path(b).exists() for b in blocks), what="the frames freed")


@linux_only
def test_a_stopped_server_ends_its_image_process_and_frees_all_it_had(tmp_path: Path) -> None:
    """SIGTERM: the app's shutdown ends the child; nothing is left for the resource
    tracker to warn of (it did, of semaphores and shared memory, with the child ended
    only at exit: uvicorn raises the signal again and the exit handlers never run)."""
    with idle_server(tmp_path) as (server, data):
        workers = _children(server.pid)
        assert workers, "no child process under the server"
        server.send_signal(signal.SIGTERM)
        server.wait(30)
    wait_until(lambda: all(has_ended(pid) for pid in workers), what="the children to end")
    log = (data / "server.log").read_text()
    assert "Application shutdown complete" in log
    assert "leaked" not in log, log[-2000:]
