"""Shared fixtures: tier one, the core on in-process fakes (unit tests only).

Every test is marked with its tier, from the directory it lives in
(tests/unit → `unit`, ...), so `pytest -m unit` runs one tier (`make test-fast`).
"""

from __future__ import annotations

import asyncio
import logging
import os
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from server.common.runtime import limit_malloc_arenas
from server.core.infra.bus import Bus
from server.core.machine.events import StartPayload
from server.core.machine.transitions import State
from server.core.operations import Operation, default_operations
from server.core.operations.safe_position import RETRACT_STEP
from server.core.worker.devices import CellDevices
from server.core.worker.worker import Worker
from server.settings.model import Settings
from server.storage import CellStores
from server.storage.journal import Journal
from server.storage.workpieces import WorkpieceIn
from tests.cpu_account import CpuAccount
from tests.fakes import FakeCamera, FakeClock, FakeGlue, FakeRobot

TESTS = Path(__file__).parent
TIERS = ("unit", "integration", "e2e", "browser", "reliability")  # registered in pyproject
# Under pytest-xdist, a module with a shared fixture runs on one worker (make test).
pytest_plugins = ["tests.xdist_groups"]


@pytest.fixture(autouse=True)
def _logging_enabled() -> Iterator[None]:
    """Undo a benchmark's `logging.disable` (the bench smoke tests call their mains in-process)."""
    yield
    logging.disable(logging.NOTSET)


def pytest_configure(config: pytest.Config) -> None:
    """Give this process the server's own allocator policy (server/common/runtime.py).

    The rig runs the server in this process, and the memory checks (test_ws_churn,
    the soak) read its RSS. Without the cap, the camera's freed frames stayed in the
    arenas of the many threads earlier tests had started, and the RSS of a WebSocket
    churn swung by two frames (47.5 MiB) either way on a busy machine.
    """
    limit_malloc_arenas()
    _terminal_size_of_the_controller(config)
    config.pluginmanager.register(CpuAccount(config), "cpu_account")


TERMINAL_SIZE = ("COLUMNS", "LINES")


@pytest.hookimpl(optionalhook=True)  # a hook of pytest-xdist's
def pytest_configure_node(node: Any) -> None:
    """pytest-xdist, on the controller: hand each worker the controller's COLUMNS and LINES."""
    for name in TERMINAL_SIZE:
        node.workerinput[name] = os.environ.get(name)


def _terminal_size_of_the_controller(config: pytest.Config) -> None:
    """In a pytest-xdist worker, COLUMNS and LINES as the controller has them.

    A worker starts with COLUMNS=80 and LINES=24 set, which its child processes inherit;
    a command-line tool that sizes its tables to a piped output when COLUMNS is unset
    (gluectl) would then cut them to 80 columns there and nowhere else.
    """
    given = getattr(config, "workerinput", None)
    if given is None:
        return
    for name in TERMINAL_SIZE:
        value = given.get(name)
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark each test with its tier: the first directory under tests/."""
    for item in items:
        try:
            tier = item.path.relative_to(TESTS).parts[0]
        except ValueError:  # collected from outside tests/
            continue
        if tier in TIERS:
            item.add_marker(getattr(pytest.mark, tier))


# A 120 × 80 mm rectangle in the library as "demo"; start it without the camera.
DEMO_OUTLINE_MM = [(340.0, -40.0), (460.0, -40.0), (460.0, 40.0), (340.0, 40.0)]
START = {"contour_matching": False, "workpiece_id": "demo"}  # the body of POST /start
START_PAYLOAD = StartPayload(contour_matching=False, workpiece_id="demo")  # the event it posts


def demo_stores(path) -> CellStores:
    """Stores under `path` with the demo workpiece in the library."""
    stores = CellStores.open(path)
    stores.workpieces.put("demo", WorkpieceIn(name="demo", outline_mm=DEMO_OUTLINE_MM))
    return stores


async def wait_for_state(worker: Worker, state: State, timeout: float = 10.0) -> None:
    """Wait until the worker reaches `state` (fails the test after `timeout`)."""
    async with asyncio.timeout(timeout):
        while worker.ctx.state is not state:
            await asyncio.sleep(0.002)


async def open_journal(path) -> Journal:
    """A real journal in a temporary file, writing on the running loop (the worker needs one)."""
    journal = Journal(path)
    journal.open()
    journal.start(asyncio.get_running_loop())
    return journal


@pytest.fixture
def fast_settings(tmp_path) -> Settings:
    return Settings(
        data_path=tmp_path / "data",
        emergency_stop_timeout=0.5,
        processing_timeout=10,
        robot_communication_timeout=1,
        glue_system_timeout=1,
        vision_processing_timeout=2,
    )


WorkerFactory = Callable[..., Awaitable[Worker]]


@pytest.fixture
async def make_worker(fast_settings: Settings, tmp_path) -> AsyncIterator[WorkerFactory]:
    """Build a started worker on fakes; waits for IDLE unless told not to."""
    workers: list[Worker] = []
    journals: list[Journal] = []

    async def factory(
        settings: Settings | None = None,
        *,
        operations: dict[str, Operation] | None = None,
        robot: FakeRobot | None = None,
        glue: FakeGlue | None = None,
        camera: FakeCamera | None = None,
        clock: FakeClock | None = None,
        wait_idle: bool = True,
    ) -> Worker:
        ops = default_operations()
        ops.update(operations or {})
        devices = CellDevices(robot or FakeRobot(), glue or FakeGlue(), camera or FakeCamera())
        journal = await open_journal(tmp_path / f"journal-{len(workers)}.db")
        journals.append(journal)
        worker = Worker(
            settings or fast_settings,
            devices,
            ops,
            Bus(),
            demo_stores(tmp_path / "worker"),
            journal=journal,
            **({"clock": clock} if clock is not None else {}),
        )
        await worker.start()
        workers.append(worker)
        if wait_idle:
            await wait_for_state(worker, State.IDLE)
        return worker

    yield factory
    for worker in workers:
        await worker.stop()
    for journal in journals:
        journal.stop()


def is_waypoint(message: dict) -> bool:
    """A bus/WebSocket/MQTT message of a run reaching its next waypoint: a progress message
    with a waypoint, other than the retract (the run's last step, which repeats the last)."""
    return (
        message.get("type", "progress") == "progress"
        and "waypoint" in message
        and message.get("step") != RETRACT_STEP
    )
