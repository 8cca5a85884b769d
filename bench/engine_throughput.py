"""Events per second through the pure engine alone, and through the worker.

The event sequence is a fixed cycle of the cell's own table (start, pause,
resume, cancel, calibrate, cancel, estop, reset, ...), so every event is
accepted and every one changes state. The worker figure includes the queue,
the engine, the history, the bus publish to one subscriber and the future
answered per event; devices are no-op fakes and operations return at once
(entering a state starts a task that is cancelled on the next event).
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.report import emit
from server.config import Settings
from server.core.bus import Bus
from server.core.devices import CellDevices
from server.core.engine import Facts, step
from server.core.transitions import Event, State
from server.core.worker import Worker
from server.drivers.base import DeviceHealth, GlueStatus, Pose
from server.storage import CellStores

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


def event_sequence(count: int) -> list[Event]:
    return [CYCLE[i % len(CYCLE)] for i in range(count)]


def bench_engine(events: list[Event]) -> float:
    facts = Facts()
    state = State.IDLE
    started = time.perf_counter()
    for event in events:
        state = step(state, event, facts).target
    return len(events) / (time.perf_counter() - started)


class NullDevice:
    """Answers every call at once; the benchmark measures the machine, not I/O."""

    pressure_range_psi = (0.0, 150.0)

    def __init__(self, name: str) -> None:
        self.health = DeviceHealth(name, connected=True)

    def set_fault_listener(self, listener: Any) -> None: ...
    async def connect(self) -> None: ...
    async def close(self) -> None: ...
    async def stop(self) -> None: ...
    async def set_valve(self, open_: bool) -> None: ...
    async def move_linear(self, *args: Any) -> None: ...
    async def get_position(self) -> Pose:
        return Pose(0, 0, 0)

    async def read_status(self) -> GlueStatus:
        return GlueStatus(False, 0, 0, 0, 0, 20, ())

    async def capture(self) -> Any:
        return None


async def instant(ctx: Any) -> dict[str, Any]:
    await asyncio.sleep(3600)  # never completes on its own; the next event ends it
    return {}


async def bench_worker(events: list[Event]) -> float:
    settings = Settings(event_queue_size=len(events) + 10, history_size=1000)
    devices = CellDevices(NullDevice("robot"), NullDevice("glue"), NullDevice("camera"))  # type: ignore[arg-type]
    operations = dict.fromkeys(
        ("trajectory", "calibrate_robot", "calibrate_camera", "create_workpiece"), instant
    )
    bus = Bus()
    bus.subscribe(maxsize=len(events) * 3)
    with tempfile.TemporaryDirectory() as directory:
        worker = Worker(settings, devices, operations, bus, CellStores.open(Path(directory)))
        return await _drive(worker, events)


async def _drive(worker: Worker, events: list[Event]) -> float:
    await worker.start()
    while worker.ctx.state is not State.IDLE:
        await asyncio.sleep(0.001)
    started = time.perf_counter()
    envelopes = [worker.submit(e, source="bench") for e in events]
    await asyncio.gather(*(e.future for e in envelopes))
    elapsed = time.perf_counter() - started
    refused = worker.stats.refused
    await worker.stop()
    assert refused == 0, f"{refused} events refused: the sequence left the table"
    return len(events) / elapsed


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--events", type=int, default=100_000)
    args = parser.parse_args(argv)
    logging.disable(logging.ERROR)  # every e-stop logs a fault; not what is measured
    events = event_sequence(args.events)
    rows = [
        {
            "what": "engine (pure step)",
            "events": len(events),
            "events_per_s": round(bench_engine(events)),
        },
        {
            "what": "worker (queue+engine+bus)",
            "events": len(events),
            "events_per_s": round(asyncio.run(bench_worker(events))),
        },
    ]
    emit("engine_throughput", rows)
    return rows


if __name__ == "__main__":
    main()
