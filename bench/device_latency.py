"""Device round trips against the simulators, through the production clients.

Round-trip time of `getPosition` (JSON-RPC/TCP) and of a Modbus status read
(RTU over TCP, 10 registers), one request at a time. The software-stop latency,
which rides on these, is bench/estop_latency.py.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import time
from typing import Any

from bench.report import emit, percentiles_ms
from server.drivers.glue_modbus import ModbusGlueDispenser
from server.drivers.robot_jsonrpc import JsonRpcRobot
from server.drivers.sim.host import SimulatorHost
from server.settings.model import Settings


async def round_trips(host: SimulatorHost, count: int) -> list[dict[str, Any]]:
    assert host.robot is not None and host.glue is not None
    robot = JsonRpcRobot("127.0.0.1", host.robot.port, timeout=2)
    glue = ModbusGlueDispenser.tcp("127.0.0.1", host.glue.port, timeout=2, poll_interval=3600)
    await robot.connect()
    await glue.connect()
    rows = []
    for name, call in (
        ("getPosition (JSON-RPC/TCP)", robot.get_position),
        ("Modbus status read (10 registers)", glue.read_status),
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


async def run(round_trip_count: int) -> list[dict[str, Any]]:
    host = SimulatorHost(Settings())
    await asyncio.to_thread(host.start)
    rows = await round_trips(host, round_trip_count)
    await asyncio.to_thread(host.stop)
    return rows


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--round-trips", type=int, default=1000)
    args = parser.parse_args(argv)
    logging.disable(logging.ERROR)
    rows = asyncio.run(run(args.round_trips))
    emit("device_latency", rows)
    return rows


if __name__ == "__main__":
    main()
