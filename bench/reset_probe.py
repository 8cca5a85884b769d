"""A reset's live probe: how long the answer takes, and that an e-stop never waits for it.

The cell runs in this process with its production clients, the robot and glue
simulators on loopback and the simulated camera (tests/rig.py), with the
default device timeouts (robot 10 s, dispenser 15 s, camera 5 s) and the
default reset_probe_timeout (2 s). Each trial puts the cell in ERROR with an
e-stop first.

Conditions:
- reset accepted: every device answers; POST /reset until its 202;
- reset refused, robot stalled: the controller swallows every request; POST
  /reset until its 409 (bounded by reset_probe_timeout, not by the robot's
  10 s);
- e-stop during a reset probe: the camera stalls, so the probe waits
  reset_probe_timeout for it; POST /estop is sent once the probe is under way
  and timed until its 202 (the reset then answers 409, overtaken).
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
from tests.rig import Rig, open_rig

DEFAULT_TIMEOUTS = {
    "robot_communication_timeout": 10.0,
    "glue_system_timeout": 15.0,
    "vision_processing_timeout": 5.0,
    "emergency_stop_timeout": 1.0,
}


async def into_error(rig: Rig) -> None:
    assert (await rig.api.post("/estop")).status_code == 202
    await rig.wait_state("ERROR")


async def timed(call: Any) -> tuple[float, Any]:
    started = time.perf_counter()
    response = await call
    return time.perf_counter() - started, response


async def reset_accepted(rig: Rig, trials: int) -> list[float]:
    samples = []
    for _ in range(trials):
        await into_error(rig)
        elapsed, response = await timed(rig.reset())
        assert response.status_code == 202, response.json()
        samples.append(elapsed)
    return samples


async def reset_refused_robot_stalled(rig: Rig, trials: int) -> list[float]:
    samples = []
    for _ in range(trials):
        rig.robot.inject_fault("stall")
        await into_error(rig)
        elapsed, response = await timed(rig.reset())
        assert response.status_code == 409, response.json()
        samples.append(elapsed)
        rig.robot.clear_faults()
        assert (await rig.reset()).status_code == 202
    return samples


async def estop_during_probe(rig: Rig, trials: int) -> list[float]:
    samples = []
    for _ in range(trials):
        await into_error(rig)
        rig.camera.inject_fault("stall")
        reset = asyncio.create_task(rig.reset())
        await asyncio.sleep(0.05)  # the probe is under way, waiting on the camera
        elapsed, response = await timed(rig.api.post("/estop"))
        assert response.status_code == 202, response.json()
        assert not reset.done(), "the e-stop was answered after the reset"
        samples.append(elapsed)
        assert (await reset).status_code == 409
        rig.camera.clear_faults()
        assert (await rig.reset()).status_code == 202
    return samples


async def run(data: Path, trials: int, slow_trials: int) -> list[dict[str, Any]]:
    async with open_rig(data, robot_heartbeat_interval=60, **DEFAULT_TIMEOUTS) as rig:
        probe_timeout = rig.cell.settings.reset_probe_timeout
        rows = [
            {
                "measure": "reset accepted (202)",
                **percentiles_ms(await reset_accepted(rig, trials)),
            },
            {
                "measure": f"reset refused, robot stalled (409; probe bound {probe_timeout:g} s)",
                **percentiles_ms(await reset_refused_robot_stalled(rig, slow_trials)),
            },
            {
                "measure": "e-stop answered during a reset probe (202)",
                **percentiles_ms(await estop_during_probe(rig, slow_trials)),
            },
        ]
    return rows


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--trials", type=int, default=50, help="accepted resets")
    parser.add_argument(
        "--slow-trials", type=int, default=5, help="refused resets and e-stops during a probe"
    )
    args = parser.parse_args(argv)
    logging.disable(logging.ERROR)
    with tempfile.TemporaryDirectory(prefix="bench-reset-") as data:
        rows = asyncio.run(run(Path(data), args.trials, args.slow_trials))
    emit("reset_probe", rows)
    return rows


if __name__ == "__main__":
    main()
