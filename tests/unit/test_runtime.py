"""The process settings `python -m server` applies (server/runtime.py)."""

from __future__ import annotations

import asyncio
import contextlib
import gc
import platform
import resource
from collections.abc import AsyncIterator

from starlette.applications import Starlette

from server.runtime import (
    GC_THRESHOLDS,
    collection_deferred,
    freeze_once_started,
    limit_malloc_arenas,
    raise_open_file_limit,
    tune_garbage_collection,
)


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
