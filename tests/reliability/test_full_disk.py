"""A full disk is refused cleanly: nothing is applied that was not saved, nothing is
answered 202 that was not journaled, the cell does not come back by itself, and the
e-stop keeps stopping.

The server runs as its own process with its data directory on a small real file
system (tests/reliability/_small_disk.py: a size-limited tmpfs where the test may
mount one, else a file-size limit on the server process); the simulators run as
their own processes. What must not happen with the journal failing: a reset or a
start answered 202 and the cell moving; PUT /workpieces or POST /tokens a bare 500; a
token revoked on a full disk revoked in memory only, and back after a restart.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest

from server.orders.model import part_of_run
from tests.conftest import demo_stores
from tests.processes import Running, server_process, simulator
from tests.reliability._small_disk import MIB, SmallDisk, small_disk
from tests.reliability.test_crash_safety import valve_reads_closed, wait_until
from tests.serving import admin_client, free_port

SPRAY_DEMO = {"contour_matching": False, "workpiece_id": "demo"}
OUTLINE = [[0.0, 0.0], [50.0, 0.0], [50.0, 30.0], [0.0, 30.0]]
REFUSED = (503, 507)  # the journal cannot write / the change could not be saved


@dataclass
class Cell:
    disk: SmallDisk
    data: Path
    glue: Running
    start_server: Callable[[], contextlib.AbstractContextManager[httpx.Client]]


@pytest.fixture
def cell_factory(tmp_path: Path) -> Iterator[Callable[..., Cell]]:
    """Builds a cell whose data directory is on a small disk (the journal too, unless
    `journal_elsewhere`), with the demo part in the library and no commissioning."""
    stack = contextlib.ExitStack()

    def build(size: int = 16 * MIB, *, journal_elsewhere: bool = False) -> Cell:
        disk = stack.enter_context(small_disk(tmp_path / "disk", size))
        data = disk.path / "data"
        demo_stores(data)
        robot = stack.enter_context(
            simulator("server.drivers.sim.robot_sim", "--speed-factor", "4")
        )
        glue = stack.enter_context(simulator("server.drivers.sim.glue_sim"))
        env = {
            "ROBOT_IP": "127.0.0.1",
            "GLUE_APP_ROBOT_PORT": str(robot.port),
            "GLUE_CONTROLLER_PORT": f"tcp://127.0.0.1:{glue.port}",
            "GLUE_APP_COMMISSION_SIMULATED_CELL": "false",
            "GLUE_APP_LOG_FILE_PATH": str(tmp_path / "logs" / "cell.log"),
        }
        if journal_elsewhere:
            env["GLUE_APP_ANALYTICS_DATABASE"] = str(tmp_path / "journal" / "journal.db")

        @contextlib.contextmanager
        def start_server() -> Iterator[httpx.Client]:
            port = free_port()
            log = tmp_path / "server.log"
            with server_process(port, data, env, log_path=log, preexec_fn=disk.preexec()) as server:
                disk.attach(server.pid)
                with admin_client(port, data) as client:
                    wait_until(lambda: state(client)["state"] == "IDLE", what="IDLE")
                    yield client

        return Cell(disk, data, glue, start_server)

    with stack:
        yield build


def state(client: httpx.Client) -> dict:
    return client.get("/state").json()


def as_token(client: httpx.Client, token: str) -> httpx.Response:
    return client.get("/state", headers={"Authorization": f"Bearer {token}"})


def message(response: httpx.Response) -> str:
    """The JSON error's text (fails the test if the answer is not JSON)."""
    body = response.json()
    return str(body.get("message") or body.get("detail") or "")


def library_edits(client: httpx.Client) -> dict[str, Callable[[], httpx.Response]]:
    part = {"name": "changed", "outline_mm": OUTLINE}
    return {
        "add a part": lambda: client.post("/workpieces", json=part),
        "replace a part": lambda: client.put("/workpieces/demo", json=part),
        "write a new part": lambda: client.put("/workpieces/spare", json=part),
    }


def assert_nothing_applied(client: httpx.Client, tokens_before: list[dict], operator: str) -> None:
    assert client.get("/tokens").json()["tokens"] == tokens_before
    assert as_token(client, operator).status_code == 200  # not revoked: it could not be saved
    assert client.get("/settings").json()["error_state_timeout"] == 300.0
    parts = client.get("/workpieces").json()
    assert [p["id"] for p in parts["workpieces"]] == ["demo"] and parts["damaged"] == []
    assert client.get("/workpieces/demo").json()["name"] == "demo"


def test_on_a_full_disk_every_change_is_refused_with_json_and_nothing_is_applied(
    cell_factory,
) -> None:
    cell = cell_factory()
    with cell.start_server() as client:
        created = client.post("/tokens", json={"name": "line", "role": "operator"}).json()
        tokens_before = client.get("/tokens").json()["tokens"]
        cell.disk.fill()
        attempts = {
            "create a token": lambda: client.post(
                "/tokens", json={"name": "late", "role": "viewer"}
            ),
            "revoke a token": lambda: client.delete(f"/tokens/{created['id']}"),
            "change a setting": lambda: client.patch("/settings", json={"error_state_timeout": 60}),
            **library_edits(client),
            "delete a part": lambda: client.delete("/workpieces/demo"),
        }
        for what, attempt in attempts.items():
            response = attempt()
            assert response.status_code in REFUSED, (what, response.status_code, response.text)
            assert "journal" in message(response), (what, response.text)
        assert_nothing_applied(client, tokens_before, created["token"])
        cell.disk.free()
        # Space again: the same changes go through, and the revocation is for good.
        assert client.delete(f"/tokens/{created['id']}").status_code == 204
        assert as_token(client, created["token"]).status_code == 401
        assert client.put("/workpieces/spare", json={"name": "s", "outline_mm": OUTLINE}).is_success
    with cell.start_server() as client:
        assert as_token(client, created["token"]).status_code == 401
        assert [t["name"] for t in client.get("/tokens").json()["tokens"]] == [
            t["name"] for t in tokens_before
        ]


def test_a_change_the_journal_allowed_but_the_disk_could_not_hold_is_a_507_and_not_applied(
    cell_factory,
) -> None:
    cell = cell_factory(journal_elsewhere=True)
    with cell.start_server() as client:
        created = client.post("/tokens", json={"name": "line", "role": "operator"}).json()
        tokens_before = client.get("/tokens").json()["tokens"]
        cell.disk.fill()
        attempts = {
            "create a token": lambda: client.post(
                "/tokens", json={"name": "late", "role": "viewer"}
            ),
            "revoke a token": lambda: client.delete(f"/tokens/{created['id']}"),
            **library_edits(client),
        }
        # On a tmpfs only the data directory is full and the journal, elsewhere, writes:
        # the change is audited, then cannot be saved. A file-size limit holds for every
        # file of the server, the journal's too: the journal refuses first (503).
        expected = (507,) if cell.disk.kind == "tmpfs" else REFUSED
        for what, attempt in attempts.items():
            response = attempt()
            assert response.status_code in expected, (what, response.status_code, response.text)
            assert message(response), (what, response.text)
        assert_nothing_applied(client, tokens_before, created["token"])
        cell.disk.free()
        if cell.disk.kind == "tmpfs":
            failed = client.get("/audit", params={"outcome": "failed (507)"}).json()["audit"]
            assert {row["action"] for row in failed} >= {"POST /tokens", "PUT /workpieces/spare"}
    with cell.start_server() as client:
        assert as_token(client, created["token"]).status_code == 200


def test_on_a_full_disk_commands_are_refused_and_the_stop_still_stops(cell_factory) -> None:
    cell = cell_factory()
    with cell.start_server() as client:
        # The first command after the disk filled is decided before anything knows:
        # its record cannot be written, so it is not a 202, and the cell stops.
        cell.disk.fill()
        first = client.post("/start", json=SPRAY_DEMO)
        assert first.status_code == 503, first.text
        assert "journal" in message(first)
        wait_until(lambda: state(client)["state"] == "ERROR", what="ERROR")
        assert state(client)["stop_reason"]["code"] == "JOURNAL_WRITE_FAILED"
        assert asyncio.run(valve_reads_closed(cell.glue.port))
        assert_reset_and_start_refused(client)
        # Space again: a reset brings the cell back, and it sprays.
        cell.disk.free()
        reset = client.post("/reset")
        assert reset.status_code == 202, reset.text
        assert state(client)["state"] == "IDLE"
        assert client.post("/start", json=SPRAY_DEMO).status_code == 202
        wait_until(lambda: cell_is_spraying(cell), what="glue flowing")
        # The disk fills while spraying: the e-stop still halts the cell at once.
        cell.disk.fill()
        stop = client.post("/estop", json={"reason": "full disk test"})
        assert stop.status_code == 202, stop.text
        assert state(client)["state"] == "ERROR"
        assert asyncio.run(valve_reads_closed(cell.glue.port))
        assert_reset_and_start_refused(client)


def cell_is_spraying(cell: Cell) -> bool:
    return not asyncio.run(valve_reads_closed(cell.glue.port))


def assert_reset_and_start_refused(client: httpx.Client) -> None:
    """A reset and a start sent together while the journal cannot write: neither goes."""
    with ThreadPoolExecutor(2) as pool:
        reset = pool.submit(client.post, "/reset")
        start = pool.submit(client.post, "/start", json=SPRAY_DEMO)
        answers = {"reset": reset.result(), "start": start.result()}
    for what, answer in answers.items():
        assert answer.status_code == 503, (what, answer.status_code, answer.text)
        assert "journal" in message(answer), (what, answer.text)
    assert state(client)["state"] == "ERROR"


def test_a_fresh_server_starts_on_a_2_mb_disk(tmp_path: Path) -> None:
    """Commissioning the simulated cell writes a 2.3 MB calibration image: on a 2 MB disk
    that step fails with a log line, and the server starts and takes commands."""
    log = tmp_path / "server.log"
    env = {"GLUE_APP_LOG_FILE_PATH": str(tmp_path / "logs" / "cell.log")}
    with small_disk(tmp_path / "disk", 2 * MIB) as disk:
        data = disk.path / "data"
        port = free_port()
        with server_process(port, data, env, log_path=log, preexec_fn=disk.preexec()):
            client = admin_client(port, data)
            wait_until(lambda: state(client)["state"] == "IDLE", what="IDLE")
            assert client.post("/home").status_code == 202
            client.close()
    assert "simulated cell not commissioned" in log.read_text()


def test_a_disk_that_fills_during_a_run_leaves_its_part_not_inspected_not_failed(
    cell_factory,
) -> None:
    """An inspection image refused with ENOSPC does not fail the run (a part sprayed whole
    would count as a failed one): the run completes and it, and the part an order makes
    of it, say the part was not inspected (no space). The journal is elsewhere
    (it has room), so only the data directory, where the images go, is full."""
    cell = cell_factory(journal_elsewhere=True)
    if cell.disk.kind != "tmpfs":
        pytest.skip("needs a tmpfs (mount rights): a file-size limit fills the journal too")
    with cell.start_server() as client:
        # The inspection maps the camera to the robot: calibrate while there is room.
        assert client.post("/calibrate-robot").status_code == 202
        wait_until(lambda: state(client)["operation"] is None, what="the calibration's end")
        assert state(client)["state"] == "IDLE", state(client)
        started = client.post("/start", json=SPRAY_DEMO)
        assert started.status_code == 202, started.text
        run_id = started.json()["run_id"]
        cell.disk.fill()
        wait_until(lambda: ended(client, run_id) is not None, what="the run's end")
        run = ended(client, run_id)
        assert run["outcome"] == "completed", (run["error"], run["result"])
        assert run["result"]["not_inspected"] == "no space", run["result"]
        assert "inspection" not in run["result"]
        [warning] = [w for w in run["result"]["warnings"] if w["code"] == "INSPECTION_NO_SPACE"]
        assert "not inspected (no space)" in warning["message"]
        # What the inspection found stands: a defect with its reasons (on a busy machine the
        # simulated bead can come out defective); a part found good is not inspected, as
        # nobody can see its image. GET /operations' `part` says the same as the order.
        found = run["result"]["inspection_found"]
        part = not_inspected_part(run)
        expected = "defective" if found["verdict"] == "defective" else "not_inspected"
        assert part["verdict"] == expected, (part, found)
        assert (run["part"]["verdict"], run["part"]["reasons"]) == (expected, part["reasons"])
        assert part["reasons"] == ["not inspected (no space)", *found["reasons"]]
        assert not list((cell.data / "inspections").glob("*.jpg"))
        cell.disk.free()


def not_inspected_part(run: dict) -> dict:
    """The part an order makes of this run (server/orders/model.py, what its report shows)."""
    part = part_of_run(
        run["run_id"], run["outcome"], run["started_at"], run["ended_at"], run["result"], None
    )
    assert (part.outcome, part.inspected) == ("completed", False)
    return part.as_dict()


def ended(client: httpx.Client, run_id: str) -> dict | None:
    """Run `run_id`'s record once it has ended (GET /operations), else None."""
    runs = client.get("/operations", params={"kind": "trajectory", "limit": 5}).json()
    for run in runs["operations"]:
        if run["run_id"] == run_id and run["ended_at"] is not None:
            return run
    return None
