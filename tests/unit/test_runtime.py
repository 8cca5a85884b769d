"""The process settings `python -m server` applies (server/common/runtime.py,
server/bootstrap/latency.py)."""

from __future__ import annotations

import asyncio
import contextlib
import gc
import os
import platform
import resource
import threading
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from starlette.applications import Starlette

from server.bootstrap.latency import GC_THRESHOLDS, freeze_once_started, tune_garbage_collection
from server.common.runtime import (
    background_held,
    background_thread,
    collection_deferred,
    limit_malloc_arenas,
    raise_open_file_limit,
)
from server.core.worker.devices import CellDevices
from server.core.worker.snapshot import SnapshotFile
from server.core.worker.stop import halt_at_once
from server.storage.journal import Journal
from tests.fakes import FakeCamera, FakeGlue, FakeRobot


def test_malloc_arenas_are_capped_where_the_c_library_is_glibc() -> None:
    assert limit_malloc_arenas() is (platform.libc_ver()[0] == "glibc")


def test_the_open_file_limit_is_raised_to_the_hard_limit() -> None:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    now = raise_open_file_limit()
    assert now >= soft
    assert resource.getrlimit(resource.RLIMIT_NOFILE)[0] == now
    if hard != resource.RLIM_INFINITY:
        assert now == hard


def test_start_up_objects_are_frozen_and_collections_are_rarer() -> None:
    thresholds = gc.get_threshold()
    try:
        tune_garbage_collection()
        assert gc.get_freeze_count() > 0
        assert gc.get_threshold() == GC_THRESHOLDS
    finally:
        gc.unfreeze()
        gc.set_threshold(*thresholds)


def test_what_start_up_builds_is_frozen_before_the_first_request() -> None:
    """An OPC UA address space built at start-up was walked by the first collection
    after it (150 ms, on the first stop pressed): start-up's heap is frozen too."""
    built: list[list[int]] = []

    @contextlib.asynccontextmanager
    async def lifespan(app: Starlette) -> AsyncIterator[None]:
        built.extend([n] for n in range(10_000))  # lists: the collector tracks each
        yield

    app = Starlette(lifespan=lifespan)
    freeze_once_started(app)

    async def start_up() -> set[int]:
        async with app.router.lifespan_context(app):
            return {id(thing) for thing in gc.get_objects()}  # what collections still walk

    thresholds = gc.get_threshold()
    try:
        walked = asyncio.run(start_up())
        assert built and not any(id(part) in walked for part in built)
    finally:
        gc.unfreeze()
        gc.set_threshold(*thresholds)


def test_a_deferred_collection_leaves_the_collector_as_it_found_it() -> None:
    assert gc.isenabled()
    with collection_deferred():
        assert not gc.isenabled()
    assert gc.isenabled()
    gc.disable()
    try:
        with collection_deferred():
            assert not gc.isenabled()
        assert not gc.isenabled()  # not turned on by a block that found it off
    finally:
        gc.enable()


LINUX_SCHEDULER = pytest.mark.skipif(
    not hasattr(os, "SCHED_BATCH"), reason="the kernel's SCHED_BATCH is Linux's"
)


def native_id_of(name: str) -> int:
    thread = next(t for t in threading.enumerate() if t.name == name)
    assert thread.native_id is not None
    return thread.native_id


async def entered_background(ids: tuple[int, ...]) -> None:
    """Return once every thread of `ids` runs inside its `background_thread` block."""
    for _ in range(500):
        with background_held():
            if all(os.sched_getscheduler(i) == os.SCHED_BATCH for i in ids):
                return
        await asyncio.sleep(0.01)
    raise AssertionError(f"threads {ids} never entered their background block")


@LINUX_SCHEDULER
def test_background_threads_are_bulk_work_only_while_held() -> None:
    inside, leave = threading.Event(), threading.Event()

    def background() -> None:
        with background_thread():
            inside.set()
            leave.wait(10)

    worker = threading.Thread(target=background, name="background")
    bystander = threading.Thread(target=leave.wait, args=(10,), name="bystander")
    worker.start()
    bystander.start()
    inside.wait(10)
    try:
        ids = native_id_of("background"), native_id_of("bystander")
        with background_held():
            held = [os.sched_getscheduler(i) for i in ids]
        released = [os.sched_getscheduler(i) for i in ids]
    finally:
        leave.set()
        worker.join()
        bystander.join()
    assert held == [os.SCHED_BATCH, os.SCHED_OTHER]
    assert released == [os.SCHED_OTHER, os.SCHED_OTHER]
    assert os.sched_getscheduler(0) == os.SCHED_OTHER  # the holder itself untouched
    with background_held():  # the thread has ended: its id is no longer held
        pass


@LINUX_SCHEDULER
async def test_the_journal_and_snapshot_writers_are_held_while_a_stop_is_sent(
    tmp_path: Path,
) -> None:
    """Woken to write, they would preempt the event loop between an e-stop's two device
    frames (docs/benchmarks.md, "Software stop"): `halt_at_once` holds them back while it
    sends both commands, and only then."""
    journal = Journal(tmp_path / "journal.db")
    journal.open()
    journal.start(asyncio.get_running_loop())
    snapshot_file = SnapshotFile(tmp_path / "state.json", interval=3600)
    snapshot_file.start()
    ids = native_id_of("journal-writer"), native_id_of("state-snapshot")
    await entered_background(ids)
    seen: dict[str, list[int]] = {}

    class Witnessing(FakeGlue):
        async def set_valve(self, open_: bool) -> None:
            seen["as the valve is closed"] = [os.sched_getscheduler(i) for i in ids]
            await super().set_valve(open_)

    try:
        halt = halt_at_once(CellDevices(FakeRobot(), Witnessing(), FakeCamera()), 1.0)
        seen["once both are sent"] = [os.sched_getscheduler(i) for i in ids]
        await halt
    finally:
        snapshot_file.stop()
        journal.stop()
    assert seen == {
        "as the valve is closed": [os.SCHED_BATCH] * 2,
        "once both are sent": [os.SCHED_OTHER] * 2,
    }
