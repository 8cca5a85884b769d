"""Live device state and glue supervision, on the simulators with the default settings.

1. How old the readings in `device` messages are while a spraying run goes on
   (the figure behind "no older than 200 ms" in docs/hardware.md): the cell
   (`Cell` with the robot and glue simulators behind the production clients,
   the simulated camera) sprays the demo part `--runs` times; every `device`
   message published while EXECUTING_TRAJECTORY is taken from the bus as it is
   published, and its `glue.age_ms` (time since the dispenser's status read)
   and `robot.age_ms` (time since the last pose read) are recorded, with the
   gap between consecutive messages.
2. How long a dispenser that falls silent with the valve open goes unnoticed:
   the production driver with the cell's default supervision against the glue
   simulator, valve open, `inject_no_reply()` at t0; the time to the
   VALVE_UNCONFIRMED report, `--silences` times (without the supervision, the same
   silence is a NO_REPLY only once the status read runs out glue_system_timeout, 15 s).
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.report import emit, percentiles_ms
from server.bootstrap.cell import Cell
from server.bootstrap.devices import glue_supervision
from server.core.machine.events import StartPayload
from server.core.machine.transitions import Command, State
from server.drivers.base import DeviceFault
from server.drivers.glue_modbus import ModbusGlueDispenser
from server.drivers.sim.glue_sim import GlueSimulator
from server.settings.model import Settings


async def feed_ages(runs: int, data: Path) -> list[dict[str, Any]]:
    settings = Settings(data_path=data)
    cell = Cell(settings)
    await cell.start()
    glue_ages: list[float] = []
    robot_ages: list[float] = []
    gaps: list[float] = []
    try:
        async with asyncio.timeout(120):
            while cell.view.state is not State.IDLE:
                await asyncio.sleep(0.05)
        subscription = cell.bus.subscribe(10_000, types=["device"])
        for _ in range(runs):
            payload = StartPayload(contour_matching=False, workpiece_id="demo")
            outcome = await cell.command(Command.START, source="bench", payload=payload)
            assert outcome.accepted, outcome
            last = None
            async with asyncio.timeout(120):
                while True:
                    message = await subscription.get()
                    state = cell.view.state
                    if state is not State.EXECUTING_TRAJECTORY:
                        if state is State.IDLE:
                            break
                        continue
                    if last is not None:
                        gaps.append(message.time - last)
                    last = message.time
                    glue, robot = message.data["glue"], message.data["robot"]
                    if glue["age_ms"] is not None:
                        glue_ages.append(glue["age_ms"] / 1000)
                    if robot["age_ms"] is not None:
                        robot_ages.append(robot["age_ms"] / 1000)
        subscription.close()
    finally:
        await cell.stop()
    return [
        {"measure": "device message: glue reading age", **percentiles_ms(glue_ages)},
        {"measure": "device message: robot pose age", **percentiles_ms(robot_ages)},
        {"measure": "device message: gap between messages", **percentiles_ms(gaps)},
    ]


async def silence_detection(silences: int) -> list[dict[str, Any]]:
    options = glue_supervision(Settings())
    samples: list[float] = []
    async with GlueSimulator() as sim:
        for _ in range(silences):
            reported = asyncio.Event()
            stamps: list[float] = []

            def listener(
                fault: DeviceFault, stamps: list[float] = stamps, reported: asyncio.Event = reported
            ) -> None:
                if fault.code == "VALVE_UNCONFIRMED" and not stamps:
                    stamps.append(time.perf_counter())
                    reported.set()

            glue = ModbusGlueDispenser.tcp("127.0.0.1", sim.port, timeout=15.0, **options)
            glue.set_fault_listener(listener)
            await glue.connect()
            await glue.set_flow_rate(30.0)
            await glue.set_pressure(40.0)
            await glue.set_valve(True)
            await asyncio.sleep(0.3)
            started = time.perf_counter()
            sim.inject_no_reply()
            async with asyncio.timeout(20):
                await reported.wait()
            samples.append(stamps[0] - started)
            sim.clear_faults()
            async with asyncio.timeout(20):  # the next trial starts with the valve closed
                await glue.set_valve(False)
            await glue.close()
    return [
        {
            "measure": f"silent with the valve open → VALVE_UNCONFIRMED "
            f"(link timeout {options['link_timeout']:g} s)",
            **percentiles_ms(samples),
        }
    ]


async def run(runs: int, silences: int) -> list[dict[str, Any]]:
    with tempfile.TemporaryDirectory(prefix="bench-device-feed-") as data:
        rows = await feed_ages(runs, Path(data))
    return rows + await silence_detection(silences)


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--runs", type=int, default=5, help="spraying runs watched")
    parser.add_argument("--silences", type=int, default=20, help="silences injected")
    args = parser.parse_args(argv)
    logging.disable(logging.ERROR)
    rows = asyncio.run(run(args.runs, args.silences))
    emit("device_feed", rows)
    return rows


if __name__ == "__main__":
    main()
