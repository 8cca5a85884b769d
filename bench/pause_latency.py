"""Pause latency: pause request → glue valve closed AND robot still, while spraying.

A trial starts a spraying run of the demo part, waits a random 0..200 ms
once glue flows, and sends PAUSE_REQUESTED to the worker (what POST /pause
posts, without the HTTP hop, which bench.estop_latency measures). It ends when
both devices hold, as the simulators recorded it:

- `valve_closed`: the glue simulator's first open → closed change after the
  request (its valve log, time.time() as the write is applied);
- `robot_still`: the end of the last motion segment the robot simulator
  recorded after the request (time.time() as the stop is applied; a move the
  run had on the line and that started after the stop is included, so this is
  when the arm really stood still for the hold);
- `total`: the later of the two, minus the moment just before the request;
- `answered`: until the worker answered PAUSED (the hold confirmed: both
  devices answered, the run's own stop and valve close done, the robot read
  still), for comparison.

Every trial checks that, when PAUSED is answered, the valve reads closed and
the robot is not moving; then the run is cancelled and the next trial starts
from IDLE.

Who runs where: the cell (its worker and the production Modbus and JSON-RPC
clients) in this process's event loop; the robot and glue simulators in a
thread of their own with their own loop (server/drivers/sim/host.py), as in
the default run; their records are read once PAUSED is answered, when they
are quiet. The simulated camera is not used (contour_matching off). Target:
p99 of `total` under 100 ms.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import random
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.report import emit, percentiles_ms
from server.bootstrap.cell import Cell
from server.core.machine.events import StartPayload
from server.core.machine.transitions import Event, State
from server.core.worker.worker import Worker
from server.drivers.sim.glue_sim import GlueSimulator
from server.drivers.sim.host import SimulatorHost
from server.drivers.sim.robot_sim import RobotSimulator
from server.settings.model import Settings

SPRAY_DEMO = StartPayload(contour_matching=False, workpiece_id="demo")
TARGET_P99_MS = 100.0


async def wait_state(worker: Worker, *states: State) -> None:
    while worker.ctx.state not in states:
        await asyncio.sleep(0.001)


async def one_pause(
    worker: Worker, robot: RobotSimulator, glue: GlueSimulator, rng: random.Random
) -> dict[str, float] | None:
    """One trial; None when the run left the spray path before the pause was sent."""
    outcome = await worker.request(Event.START_REQUESTED, source="bench", payload=SPRAY_DEMO)
    assert outcome.accepted, outcome.message
    while not glue.valve_open:
        await asyncio.sleep(0.001)
    await asyncio.sleep(rng.uniform(0.0, 0.2))
    if not glue.valve_open:  # between two spray lines, or done
        result = None
    else:
        sent = time.time()
        paused = await worker.request(Event.PAUSE_REQUESTED, source="bench")
        answered = time.time()
        assert paused.state is State.PAUSED, paused.message
        assert not glue.valve_open and not robot.is_moving, "PAUSED before the devices held"
        closes = [at for at, is_open in glue.valve_log if not is_open and at >= sent]
        closed = min(closes) if closes else sent  # the run closed it just before
        still = max([s.t_end for s in robot.executed_path if s.t_end >= sent] or [sent])
        result = {
            "total": max(closed, still) - sent,
            "valve_closed": closed - sent,
            "robot_still": still - sent,
            "answered": answered - sent,
        }
    await worker.request(Event.CANCEL_REQUESTED, source="bench")
    await wait_state(worker, State.IDLE)
    return result


async def run(trials: int, speed_factor: float, seed: int) -> list[dict[str, Any]]:
    data = Path(tempfile.mkdtemp(prefix="bench-pause-"))
    host = SimulatorHost(Settings(simulation_speed_factor=speed_factor, data_path=data))
    await asyncio.to_thread(host.start)
    robot, glue = host.robot, host.glue
    assert robot is not None and glue is not None
    settings = Settings(
        robot_ip="127.0.0.1",
        robot_port=robot.port,
        glue_controller_port=f"tcp://127.0.0.1:{glue.port}",
        robot_communication_timeout=1.0,
        glue_system_timeout=1.0,
        data_path=data,
    )
    cell = Cell(settings)
    samples: dict[str, list[float]] = {
        "total": [],
        "valve_closed": [],
        "robot_still": [],
        "answered": [],
    }
    skipped = 0
    try:
        await cell.start()
        worker = cell.worker
        assert worker is not None
        await wait_state(worker, State.IDLE)
        rng = random.Random(seed)
        while len(samples["total"]) < trials:
            # Between trials the simulators are quiet (IDLE, valve closed), so their
            # records are read and cleared from this thread without racing theirs.
            glue.valve_log.clear()
            robot.clear_path()
            result = await one_pause(worker, robot, glue, rng)
            if result is None:
                skipped += 1
                continue
            for key, value in result.items():
                samples[key].append(value)
    finally:
        await cell.stop()
        await asyncio.to_thread(host.stop)
        shutil.rmtree(data, ignore_errors=True)  # a journal per run: not worth keeping
    return [
        {
            "measure": key,
            **percentiles_ms(values),
            **({"target_p99_ms": TARGET_P99_MS} if key == "total" else {}),
            **({"skipped": skipped} if key == "total" else {}),
        }
        for key, values in samples.items()
    ]


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--trials", type=int, default=200, help="pauses while spraying")
    parser.add_argument(
        "--speed-factor", type=float, default=4.0, help="robot simulator speed (as the rig)"
    )
    parser.add_argument("--seed", type=int, default=20261123)
    args = parser.parse_args(argv)
    # Every pause logs the driver's stop, and pymodbus an error when the cell's link
    # closes at the end; not what is measured (bench.estop_latency does the same).
    logging.disable(logging.ERROR)
    rows = asyncio.run(run(args.trials, args.speed_factor, args.seed))
    emit("pause_latency", rows, {"trials": args.trials, "speed_factor": args.speed_factor})
    return rows


if __name__ == "__main__":
    main()
