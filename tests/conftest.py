"""Shared fixtures: tier one, the core on in-process fakes (unit tests only)."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Awaitable, Callable

import pytest

from server.config import Settings
from server.core.bus import Bus
from server.core.devices import CellDevices
from server.core.operations import Operation, default_operations
from server.core.transitions import State
from server.core.worker import Worker
from tests.fakes import FakeCamera, FakeGlue, FakeRobot


async def wait_for_state(worker: Worker, state: State, timeout: float = 10.0) -> None:
    """Wait until the worker reaches `state` (fails the test after `timeout`)."""
    async with asyncio.timeout(timeout):
        while worker.ctx.state is not state:
            await asyncio.sleep(0.002)


@pytest.fixture
def fast_settings() -> Settings:
    return Settings(
        emergency_stop_timeout=0.5,
        processing_timeout=10,
        robot_communication_timeout=1,
        glue_system_timeout=1,
        vision_processing_timeout=2,
    )


WorkerFactory = Callable[..., Awaitable[Worker]]


@pytest.fixture
async def make_worker(fast_settings: Settings) -> AsyncIterator[WorkerFactory]:
    """Build a started worker on fakes; waits for IDLE unless told not to."""
    workers: list[Worker] = []

    async def factory(
        settings: Settings | None = None,
        *,
        operations: dict[str, Operation] | None = None,
        robot: FakeRobot | None = None,
        glue: FakeGlue | None = None,
        camera: FakeCamera | None = None,
        wait_idle: bool = True,
    ) -> Worker:
        ops = default_operations()
        ops.update(operations or {})
        devices = CellDevices(robot or FakeRobot(), glue or FakeGlue(), camera or FakeCamera())
        worker = Worker(settings or fast_settings, devices, ops, Bus())
        await worker.start()
        workers.append(worker)
        if wait_idle:
            await wait_for_state(worker, State.IDLE)
        return worker

    yield factory
    for worker in workers:
        await worker.stop()
