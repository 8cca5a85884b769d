"""Device round trips and the software-stop latency, measured where it matters.

1. Round-trip time of `getPosition` (JSON-RPC/TCP) and of a Modbus status read
   (RTU over TCP) against the simulators, through the production clients.
2. E-stop latency: from the moment the client sends POST /estop to the moment
   the robot simulator has received `stop` AND the glue simulator's valve
   register reads closed (both simulators stamp time.time() on arrival). The
   server, the simulators and the client each run apart (the server in this
   process's main loop, the simulators in their own thread, the client in
   another thread), measured in two conditions:
   - idle: the cell in IDLE;
   - running + full queue: a trajectory spraying and the event queue filled to
     event_queue_size with requests just before the stop.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
import uvicorn

from bench.report import emit, percentiles_ms
from server.app import create_app
from server.cell import Cell
from server.config import Settings
from server.core.transitions import Event, State
from server.drivers.glue_modbus import ModbusGlueDispenser
from server.drivers.robot_jsonrpc import JsonRpcRobot
from server.drivers.sim.host import SimulatorHost
from server.errors import EventQueueFull
from tests.serving import free_port


async def round_trips(host: SimulatorHost, count: int) -> list[dict[str, Any]]:
    assert host.robot is not None and host.glue is not None
    robot = JsonRpcRobot("127.0.0.1", host.robot.port, timeout=2)
    glue = ModbusGlueDispenser.tcp("127.0.0.1", host.glue.port, timeout=2, poll_interval=3600)
    await robot.connect()
    await glue.connect()
    rows = []
    for name, call in (
        ("getPosition (JSON-RPC/TCP)", robot.get_position),
        ("Modbus status read (8 registers)", glue.read_status),
    ):
        samples = []
        for _ in range(count):
            started = time.perf_counter()
            await call()
            samples.append(time.perf_counter() - started)
        rows.append({"measure": f"round trip: {name}", **percentiles_ms(samples)})
    await robot.close()
    await glue.close()
    return rows


def estop_once(client: httpx.Client, host: SimulatorHost) -> float:
    """Send POST /estop; the time until both simulators saw the stop."""
    assert host.robot is not None and host.glue is not None
    sent = time.time()
    response = client.post("/estop")
    assert response.status_code == 202, response.text
    deadline = time.time() + 5
    while True:
        robot_at, valve_at = host.robot.last_stop_at, host.glue.close_commanded_at
        if robot_at and valve_at and robot_at >= sent and valve_at >= sent:
            assert not host.glue.valve_open
            return max(robot_at, valve_at) - sent
        if time.time() > deadline:
            raise RuntimeError("the stop never reached both simulators")
        time.sleep(0.0005)


async def wait_state(cell: Cell, state: State) -> None:
    assert cell.worker is not None
    while cell.worker.ctx.state is not state:
        await asyncio.sleep(0.002)


async def estop_trials(trials: int, queue_size: int) -> list[dict[str, Any]]:
    host = SimulatorHost(Settings(simulation_speed_factor=3))
    await asyncio.to_thread(host.start)
    assert host.robot is not None and host.glue is not None
    settings = Settings(
        robot_ip="127.0.0.1",
        robot_port=host.robot.port,
        glue_controller_port=f"tcp://127.0.0.1:{host.glue.port}",
        event_queue_size=queue_size,
        emergency_stop_timeout=1.0,
        data_path=Path(tempfile.mkdtemp(prefix="bench-cell-")),
    )
    cell = Cell(settings)
    port = free_port()
    server = uvicorn.Server(
        uvicorn.Config(
            create_app(cell=cell),
            host="127.0.0.1",
            port=port,
            log_level="error",
            ws="websockets-sansio",
        )
    )
    serving = asyncio.create_task(server.serve())
    while not server.started:
        await asyncio.sleep(0.01)
    token = (settings.data_path / "admin.token").read_text().strip()
    client = httpx.Client(
        base_url=f"http://127.0.0.1:{port}",
        timeout=10,  # a kept-alive HMI
        headers={"Authorization": f"Bearer {token}"},
    )
    await wait_state(cell, State.IDLE)
    worker = cell.worker
    assert worker is not None
    rows = []
    for condition in ("idle", "running + full queue"):
        samples = []
        for _ in range(trials):
            if worker.ctx.state is State.ERROR:
                assert (await worker.request(Event.RESET_REQUESTED, source="bench")).accepted
            await wait_state(cell, State.IDLE)
            host.robot.last_stop_at = None
            host.glue.close_commanded_at = None
            if condition != "idle":
                await worker.request(
                    Event.START_REQUESTED,
                    source="bench",
                    data={"contour_matching": False, "workpiece_id": "demo"},
                )
                while not host.glue.valve_open:
                    await asyncio.sleep(0.002)
                try:
                    while True:
                        worker.submit(Event.PAUSE_REQUESTED, source="bench")
                except EventQueueFull:
                    pass
            samples.append(await asyncio.to_thread(estop_once, client, host))
        rows.append({"measure": f"e-stop latency: {condition}", **percentiles_ms(samples)})
    await asyncio.to_thread(client.close)
    server.should_exit = True
    await serving
    await asyncio.to_thread(host.stop)
    return rows


async def run(trials: int, round_trip_count: int, queue_size: int) -> list[dict[str, Any]]:
    host = SimulatorHost(Settings())
    await asyncio.to_thread(host.start)
    rows = await round_trips(host, round_trip_count)
    await asyncio.to_thread(host.stop)
    return rows + await estop_trials(trials, queue_size)


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--trials", type=int, default=200, help="e-stops per condition")
    parser.add_argument("--round-trips", type=int, default=1000)
    parser.add_argument("--queue-size", type=int, default=1000)
    args = parser.parse_args(argv)
    logging.disable(logging.ERROR)
    rows = asyncio.run(run(args.trials, args.round_trips, args.queue_size))
    emit("device_latency", rows, {"trials": args.trials, "queue_size": args.queue_size})
    return rows


if __name__ == "__main__":
    main()
