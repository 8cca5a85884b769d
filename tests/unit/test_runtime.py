"""The process settings `python -m server` applies (server/runtime.py)."""

from __future__ import annotations

import gc
import platform
import resource

from server.runtime import (
    GC_THRESHOLDS,
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
