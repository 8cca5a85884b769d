"""Events per second through the pure engine, two state-machine libraries, and the worker.

The event sequence is a fixed cycle of the cell's own table (start, pause,
resume, cancel, calibrate, cancel, estop, reset, ...), so every event is
accepted and every one changes state. The same sequence, in the same run, goes
through:

- the engine: `step(state, event, facts)`, guards included;
- `transitions` and `python-statemachine`, each given the cell's table
  (built from `server.core.machine.transitions`, guards as conditions that hold), with
  no callbacks beyond the guards: their fastest honest configuration;
- the worker: the queue, the engine, the history, the snapshot, the bus publish
  to one subscriber and the future answered per event, with the cell's entry and
  exit actions on no-op devices (entering an operational state starts an
  operation task, which the next event cancels; every stop runs the safe halt;
  a reset probes the devices).

`--profile` adds where the worker's time goes (cProfile, cumulative seconds of
the worker's own functions over a shorter run).
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import logging
import pstats
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.report import emit
from server.core.infra.bus import Bus
from server.core.machine.engine import Facts, step
from server.core.machine.events import StartPayload
from server.core.machine.transitions import Event, Guard, State, transitions
from server.core.worker.devices import CellDevices
from server.core.worker.event_queue import Envelope
from server.core.worker.worker import Worker
from server.drivers.base import DeviceHealth, GlueStatus, Pose
from server.settings.model import Settings
from server.storage import CellStores
from server.storage.workpieces import WorkpieceIn

CYCLE = [
    Event.START_REQUESTED,
    Event.PAUSE_REQUESTED,
    Event.RESUME_REQUESTED,
    Event.CANCEL_REQUESTED,
    Event.CALIBRATE_ROBOT_REQUESTED,
    Event.CANCEL_REQUESTED,
    Event.EMERGENCY_STOP,
    Event.RESET_REQUESTED,
]


# Each run sprays the library's demo part where it is stored (no camera, no calibration
# needed), so every start is accepted: the cycle measures the machine, not refusals.
START_DEMO = StartPayload(contour_matching=False, workpiece_id="demo")
DEMO_PART = WorkpieceIn(
    name="demo", outline_mm=[(340.0, -40.0), (460.0, -40.0), (460.0, 40.0), (340.0, 40.0)]
)


def event_sequence(count: int) -> list[Event]:
    return [CYCLE[i % len(CYCLE)] for i in range(count)]


def submit(worker: Worker, event: Event) -> Envelope:
    """Queue one event of the cycle with the payload it needs."""
    payload = START_DEMO if event is Event.START_REQUESTED else None
    return worker.submit(event, source="bench", payload=payload)


async def submit_all(worker: Worker, events: list[Event]) -> None:
    """Queue the events, waiting for each reset's answer before what follows it.

    Why wait there: a reset probes the devices while the worker goes on with the
    queue, so a start queued behind it would find the cell still in ERROR.
    """
    pending: list[Envelope] = []
    for event in events:
        pending.append(submit(worker, event))
        if event is Event.RESET_REQUESTED:
            await asyncio.gather(*(e.future for e in pending if e.future is not None))
            pending = []
    await asyncio.gather(*(e.future for e in pending if e.future is not None))


def stores_with_demo(directory: Path) -> CellStores:
    stores = CellStores.open(directory)
    stores.workpieces.put("demo", DEMO_PART)
    return stores


def bench_engine(events: list[Event]) -> float:
    facts = Facts()
    state = State.IDLE
    started = time.perf_counter()
    for event in events:
        state = step(state, event, facts).target
    return len(events) / (time.perf_counter() - started)


GUARD_NAMES = {Guard.ALL_DEVICES_READY: "all_devices_ready", Guard.FAULTS_CLEARED: "faults_cleared"}


class GuardsHold:
    """The model the libraries consult for the table's guards; both always hold here."""

    def all_devices_ready(self, *_: Any, **__: Any) -> bool:
        return True

    def faults_cleared(self, *_: Any, **__: Any) -> bool:
        return True


def bench_transitions(events: list[Event]) -> float:
    """The `transitions` library's Machine over the cell's table."""
    from transitions import Machine

    spec = []
    for row in transitions():
        rule: dict[str, Any] = {
            "trigger": row.event.value,
            "source": row.source.value,
            "dest": row.target.value,
        }
        if row.guard is not None:
            rule["conditions"] = GUARD_NAMES[row.guard]
        spec.append(rule)
    model = GuardsHold()
    Machine(
        model=model,
        states=[s.value for s in State],
        transitions=spec,
        initial=State.IDLE.value,
        auto_transitions=False,
    )
    names = [e.value for e in events]
    trigger = model.trigger  # type: ignore[attr-defined]
    started = time.perf_counter()
    for name in names:
        trigger(name)
    return len(names) / (time.perf_counter() - started)


def bench_python_statemachine(events: list[Event]) -> float:
    """`python-statemachine`: a StateMachine class generated from the cell's table."""
    from statemachine import State as LibState
    from statemachine import StateMachine

    # The library insists every state be reachable from the initial one, so the
    # machine starts in INITIALIZING and is brought to IDLE before timing.
    states = {s: LibState(s.value, initial=s is State.INITIALIZING, value=s.value) for s in State}
    namespace: dict[str, Any] = {s.value: lib_state for s, lib_state in states.items()}
    for row in transitions():
        guard = [GUARD_NAMES[row.guard]] if row.guard is not None else None
        edge = states[row.source].to(states[row.target], cond=guard)
        name = row.event.value
        namespace[name] = namespace[name] | edge if name in namespace else edge
    namespace.update(all_devices_ready=GuardsHold.all_devices_ready)
    namespace.update(faults_cleared=GuardsHold.faults_cleared)
    machine = type("CellTable", (StateMachine,), namespace)()
    machine.send(Event.SYSTEM_READY.value)
    names = [e.value for e in events]
    send = machine.send
    started = time.perf_counter()
    for name in names:
        send(name)
    return len(names) / (time.perf_counter() - started)


class NullDevice:
    """Answers every call at once; the benchmark measures the machine, not I/O."""

    pressure_range_psi = (0.0, 150.0)

    def __init__(self, name: str) -> None:
        self.health = DeviceHealth(name, connected=True)

    def set_fault_listener(self, listener: Any) -> None: ...
    def new_session(self) -> int:
        return 0

    def drop_waiting_openings(self) -> int:
        return 0

    async def connect(self) -> None: ...
    async def close(self) -> None: ...
    async def stop(self) -> None: ...
    async def set_valve(self, open_: bool) -> None: ...
    async def move_linear(self, *args: Any) -> None: ...
    async def is_moving(self) -> bool:
        return False

    async def get_position(self) -> Pose:
        return Pose(0, 0, 0)

    async def read_status(self) -> GlueStatus:
        return GlueStatus(False, 0, 0, 0, 0, 20, ())

    async def capture(self) -> Any:
        return None


class NullJournal:
    """Takes every record and writes none: the worker's own cost, without the disk's.

    Why: the worker benchmark measures deciding and acting; the journal's cost
    is measured apart, level by level, in bench/journal.py.
    """

    backlog = 0
    last_error = None
    damage: tuple[Any, ...] = ()
    path = Path("/nonexistent/journal.db")  # no file: the wear counters start from zero

    def append(self, records: list[Any], *, durable: bool = True) -> None:
        return None


async def instant(ctx: Any) -> dict[str, Any]:
    await asyncio.sleep(3600)  # never completes on its own; the next event ends it
    return {}


def new_worker(directory: Path, queue_size: int) -> Worker:
    """A worker on no-op devices, with operations that run until the next event."""
    settings = Settings(event_queue_size=queue_size, history_size=1000)
    devices = CellDevices(NullDevice("robot"), NullDevice("glue"), NullDevice("camera"))  # type: ignore[arg-type]
    operations = dict.fromkeys(
        ("trajectory", "calibrate_robot", "calibrate_camera", "create_workpiece"), instant
    )
    bus = Bus()
    bus.subscribe(maxsize=queue_size * 3)
    stores = stores_with_demo(directory)
    return Worker(settings, devices, operations, bus, stores, journal=NullJournal())  # type: ignore[arg-type]


async def bench_worker(events: list[Event]) -> float:
    with tempfile.TemporaryDirectory() as directory:
        return await _drive(new_worker(Path(directory), len(events) + 10), events)


async def _drive(worker: Worker, events: list[Event]) -> float:
    await worker.start()
    while worker.ctx.state is not State.IDLE:
        await asyncio.sleep(0.001)
    started = time.perf_counter()
    await submit_all(worker, events)
    elapsed = time.perf_counter() - started
    refused = worker.stats.refused
    await worker.stop()
    assert refused == 0, f"{refused} events refused: the sequence left the table"
    return len(events) / elapsed


PROFILE_GROUPS = (
    ("engine (server/core/machine/engine.py)", "/server/core/machine/engine.py"),
    ("worker, bus, context (rest of server/core)", "/server/core/"),
    ("asyncio loop, tasks, futures", "/asyncio/"),
    ("benchmark's no-op devices and operations", "/bench/"),
)


def profile_worker(events: list[Event]) -> list[dict[str, Any]]:
    """Where the worker's time goes: own time (cProfile tottime) summed by area."""
    profiler = cProfile.Profile()
    profiler.enable()
    asyncio.run(bench_worker(events))
    profiler.disable()
    totals: dict[str, float] = {}
    for (filename, _, _), (_, _, own, _, _) in pstats.Stats(profiler).stats.items():  # type: ignore[attr-defined]
        area = next(
            (name for name, part in PROFILE_GROUPS if part in filename),
            "other (builtins, logging, dataclasses, ...)",
        )
        totals[area] = totals.get(area, 0.0) + own
    whole = sum(totals.values())
    return [
        {
            "area": area,
            "us_per_event": round(seconds / len(events) * 1e6, 2),
            "share": f"{seconds / whole:.0%}",
        }
        for area, seconds in sorted(totals.items(), key=lambda item: item[1], reverse=True)
    ]


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--events", type=int, default=100_000)
    parser.add_argument("--profile", action="store_true", help="profile the worker too")
    args = parser.parse_args(argv)
    logging.disable(logging.ERROR)  # every e-stop logs a fault; not what is measured
    events = event_sequence(args.events)
    measured = {
        "engine (pure step)": bench_engine(events),
        "transitions (library)": bench_transitions(events),
        "python-statemachine (library)": bench_python_statemachine(events),
        "worker (queue+engine+actions+bus)": asyncio.run(bench_worker(events)),
    }
    fastest_library = max(
        measured["transitions (library)"], measured["python-statemachine (library)"]
    )
    rows = [
        {
            "what": what,
            "events": len(events),
            "events_per_s": round(rate),
            "x_fastest_library": round(rate / fastest_library, 2),
        }
        for what, rate in measured.items()
    ]
    extra: dict[str, Any] = {}
    if args.profile:
        extra["worker_profile"] = profile_worker(events[: max(len(events) // 5, len(CYCLE))])
        emit("engine_throughput_worker_profile", extra["worker_profile"])
    emit("engine_throughput", rows, extra)
    return rows


if __name__ == "__main__":
    main()
