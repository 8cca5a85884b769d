"""The cell's start does at once what need not wait for each other.

Building the devices (the simulators started, each client made) and opening the
journal (checked: a second on a large one) are both mostly a thread's wait, and
neither needs the other: `Cell.start` runs them together. Seen here with a device
factory that finishes only once the journal exists: one after the other, the
start could never end.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Awaitable, Callable

import pytest

from server.bootstrap.cell import Cell
from server.core.machine.transitions import State
from server.core.worker.devices import CellDevices
from server.settings.model import Settings
from tests.fakes import FakeCamera, FakeGlue, FakeRobot

BOUND_S = 30.0  # a bound on the wait, never a performance assertion


def settings_for(fast_settings: Settings) -> Settings:
    # A camera by address: the fakes stand for the devices, no image process is started.
    return fast_settings.model_copy(update={"vision_camera_id": "0"})


async def test_the_devices_are_built_while_the_journal_is_opened(
    fast_settings: Settings,
) -> None:
    settings = settings_for(fast_settings)
    released: list[bool] = []

    async def release() -> None:
        released.append(True)

    async def once_the_journal_exists(
        settings: Settings,
    ) -> tuple[CellDevices, Callable[[], Awaitable[None]]]:
        async with asyncio.timeout(BOUND_S):
            while not settings.journal_file.exists():
                await asyncio.sleep(0.01)
        return CellDevices(FakeRobot(), FakeGlue(), FakeCamera()), release  # type: ignore[arg-type]

    cell = Cell(settings, device_factory=once_the_journal_exists)
    await cell.start()
    try:
        async with asyncio.timeout(BOUND_S):
            while cell.view.state is not State.IDLE:
                await asyncio.sleep(0.01)
    finally:
        await cell.stop()
    assert released == [True]


async def test_a_start_whose_devices_fail_stops_the_journal_it_opened(
    fast_settings: Settings,
) -> None:
    settings = settings_for(fast_settings)

    async def fails(settings: Settings) -> tuple[CellDevices, Callable[[], Awaitable[None]]]:
        await asyncio.sleep(0)
        raise OSError("the robot simulator's port is taken")

    before = set(threading.enumerate())
    cell = Cell(settings, device_factory=fails)
    with pytest.raises(OSError, match="port is taken"):
        await cell.start()
    left = {thread.name for thread in set(threading.enumerate()) - before if thread.is_alive()}
    assert not left & {"journal-writer", "state-snapshot"}, "the records' threads outlive it"
