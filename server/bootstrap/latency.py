"""What keeps the e-stop fast: the process-wide parts, applied here; the rest, listed at its door.

A stop is measured from its arrival to both devices' halt frames on their
sockets: by condition in `bench.estop_latency` (idle, a run, a full queue, a
WebSocket crowd), by door in `bench.estop_doors` (HTTP, MQTT, OPC UA).

Applied here, by `install`, which the composition root
(`server/bootstrap/app.py: create_app`) calls once for the app it builds:

- Routes prepared at start-up (`server/api/route_warmup.py: prepare_routes`),
  beside the app's start and done before the port opens. FastAPI prepares a
  route the first time a request is matched against it; the first POST /estop
  would prepare every route ahead of it before its handler ran
  (tests/integration/test_first_stop.py; bench.estop_latency's first trial).
- With `tune_process` (`python -m server`, and the benchmarks that measure the
  server as it runs; never a test process, which holds many cells):
  - garbage collection: everything alive once the app is built (modules,
    routes, schemas, the vision and protocol libraries) is frozen out of the
    collector, and collections run rarer (`GC_THRESHOLDS`: generation 0 every
    10 000 net allocations instead of 700; the older ones 50 and 100 times
    rarer instead of 10). Collections of the heap a WebSocket crowd makes
    are the longest pauses the loop meets, stops included: with Python's
    defaults the fan-out's p99 is more than twice as long (bench/ws_fanout.py).
    Reference counting still frees nearly all garbage at once, and
    bench/memory.py shows memory levels off.
  - the same again once the app has started: what the start built (the cell,
    the journal, OPC UA's address space) came after the first freeze, and the
    first collection of the older generations would walk all of it, on
    whatever came first, such as the first stop (with OPC UA about 150 ms,
    bench/plant_latency.py).
- The interpreter's thread switch interval (`sys.setswitchinterval`) is left at
  its default: the stop's frames are written from the event loop's own
  thread, and the threads that could take the interpreter from it are held
  back for those microseconds at the door instead (below).

At its door, because each is how that door reads a stop (they stay there):

- HTTP, the stop made and answered just after the access check, its halt begun
  before its body is read, and no body limit, routing or route on its way:
  `server/api/door.py: HttpDoor` hands it to `server/api/stop_lane.py:
  StopLane.stop` (bench.estop_latency); its task first in the loop's line as
  its headers are read, ahead of a flood's requests read before it:
  `server/api/connection_guard.py: _first_in_line` (bench.estop_doors).
- The halt itself, a task whose first step has run, with no collection and no
  background thread in between: `server/core/worker/stop.py:
  EmergencyStops.begin` and `halt_at_once`, `server/core/infra/eager.py:
  start_task`, `server/common/runtime.py: collection_deferred` and
  `background_held` (bench.estop_latency).
- JSON answers built directly, not through FastAPI's response model path:
  `server/api/stop_lane.py: StopLane.stop` (the stop's 202),
  `server/api/commands.py: _answer` (the other commands') and
  `server/api/direct_json.py: DirectJsonRoute` (GET /state;
  bench.rest_throughput).
- MQTT, a stop taken out of the client's incoming queue as it is parsed, on a
  connection of its own: `server/mqtt/link.py: StopFirstQueue` and
  `MqttLink._stop_at_once`; the other commands served a few at a time
  (`MqttLink._listen`, `ADMITTED`), so a flood does not make the loop's turns
  long ahead of the stop lane's socket (bench.estop_doors).
- OPC UA, a session's calls served side by side, a few at a time, the rest in a
  line a stop overtakes, its first step at once: `server/opcua/call_lane.py:
  CallLane._take_call` (bench.estop_doors).
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
from collections.abc import AsyncIterator
from typing import Any

from fastapi import FastAPI
from starlette.applications import Starlette

from server.api.route_warmup import prepare_routes

GC_THRESHOLDS = (10_000, 50, 100)


def install(app: FastAPI, *, tune_process: bool = False) -> None:
    """Prepare `app`'s routes beside its start; with `tune_process`, also tune this
    process's garbage collection now and once the app has started (module docstring)."""
    prepare_routes_at_start(app)
    if tune_process:
        tune_garbage_collection()
        freeze_once_started(app)


def prepare_routes_at_start(app: FastAPI) -> None:
    """Wrap the app's lifespan: every route prepared while it starts, before the port opens.

    The preparation yields to the loop between routes, so it runs beside the
    cell's start (its devices connecting); the start fails as it did if either
    fails."""
    starting = app.router.lifespan_context

    @contextlib.asynccontextmanager
    async def lifespan(app: Any) -> AsyncIterator[Any]:
        preparing = asyncio.create_task(prepare_routes(app), name="route-preparation")
        try:
            async with starting(app) as state:
                await preparing
                yield state
        finally:
            preparing.cancel()

    app.router.lifespan_context = lifespan


def tune_garbage_collection() -> None:
    """Collect once, exempt every surviving object from later collections, collect rarely."""
    gc.collect()
    gc.freeze()
    gc.set_threshold(*GC_THRESHOLDS)


def freeze_once_started(app: Starlette) -> None:
    """Collect and freeze again when the app's start-up completes (module docstring).

    It wraps the app's lifespan rather than the app, so requests pay nothing for it."""
    started = app.router.lifespan_context

    @contextlib.asynccontextmanager
    async def lifespan(app: Any) -> AsyncIterator[Any]:
        async with started(app) as state:
            tune_garbage_collection()
            yield state

    app.router.lifespan_context = lifespan
