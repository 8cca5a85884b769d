"""The devices and the HMI of the stop benchmark, in a process of their own.

`python -m bench.stop_witness` starts the robot and glue simulators on free
loopback ports and prints "robot <port> glue <port>". It then reads commands
on its standard input:

- "server <base_url> <token>": the server to stop, once it is up (connected to
  with one GET /state before "ready" is printed);
- "arm": clear the simulators' stop stamps and print "armed" (a stop sent by
  another door follows);
- "stamps": wait (up to 30 s) until the robot has received `stop` and the
  dispenser a valve-close write since "arm", and print "stamps <robot_at> <glue_at>"
  ("stamps none none" if they did not come);
- "fire": clear the simulators' stop stamps, send POST /estop (on a kept-alive
  connection, as an HMI holds one), and print
  "stopped <seconds> <valve_closed> <sent_at> <answered> <robot_at> <glue_at>":
  from just before the request left to the later of the robot receiving its
  first `stop` and the dispenser its first valve-close write after it (both
  stamped with time.time() by the simulators on arrival); `answered` is the
  request's round trip (seconds until its answer was read), then the two stamps.
  The first, watched while the answer is on its way: the simulators keep only
  the latest stamp, and a stop while spraying may be followed by another close
  (the run's own, when the halt could not confirm the valve closed). Reading
  the stamps once the answer had come measured the last of them: a run whose
  cancellation took emergency_stop_timeout showed as a 1 s stop.

Being a separate process matters: simulators or a client inside the server's
process would wait for its interpreter lock while it works, and that wait
would be charged to the server's stop latency. Real devices and HMIs share no
lock with the server. Here one event loop holds the client and both
simulators, and it is idle while a stop is on its way.
"""

from __future__ import annotations

import asyncio
import sys
import time

import httpx

from server.drivers.sim.glue_sim import GlueSimulator
from server.drivers.sim.robot_sim import RobotSimulator
from server.settings.model import Settings


async def fire(client: httpx.AsyncClient, robot: RobotSimulator, glue: GlueSimulator) -> str:
    robot.last_stop_at = None
    glue.close_commanded_at = None
    sent = time.time()
    answer = asyncio.ensure_future(client.post("/estop"))
    # The first stop and close to arrive, not the last: a cancelled run may send
    # its own close before the answer comes.
    robot_at = glue_at = None
    while not (robot_at and glue_at) and not answer.done():
        robot_at = robot_at or robot.last_stop_at
        glue_at = glue_at or glue.close_commanded_at
        await asyncio.sleep(0.0002)  # when we report, not what we report
    response = await answer
    answered = time.time() - sent
    if response.status_code != 202:
        return f"failed {response.status_code} {response.text[:200]!r}"
    while not (robot_at and glue_at):  # the answer came first: wait for the stamps
        robot_at = robot_at or robot.last_stop_at
        glue_at = glue_at or glue.close_commanded_at
        await asyncio.sleep(0.0002)
    latency = max(robot_at, glue_at) - sent
    return f"stopped {latency} {not glue.valve_open} {sent} {answered} {robot_at} {glue_at}"


async def stamps(robot: RobotSimulator, glue: GlueSimulator) -> str:
    """The first stop and close since "arm" (`fire` says why the first)."""
    robot_at = glue_at = None
    deadline = time.monotonic() + 30.0
    while not (robot_at and glue_at) and time.monotonic() < deadline:
        robot_at = robot_at or robot.last_stop_at
        glue_at = glue_at or glue.close_commanded_at
        await asyncio.sleep(0.0002)
    return f"stamps {robot_at} {glue_at}"


async def witness(speed_factor: float) -> None:
    settings = Settings()
    async with (
        RobotSimulator(
            "127.0.0.1",
            0,
            workspace_min=settings.workspace_min_mm,
            workspace_max=settings.workspace_max_mm,
            home=settings.safe_position,
            speed_factor=speed_factor,
        ) as robot,
        GlueSimulator("127.0.0.1", 0, speed_factor=speed_factor) as glue,
    ):
        print(f"robot {robot.port} glue {glue.port}", flush=True)
        loop = asyncio.get_running_loop()
        client: httpx.AsyncClient | None = None
        try:
            while True:
                words = (await loop.run_in_executor(None, sys.stdin.readline)).split()
                if not words:
                    return  # end of input: the benchmark is done
                if words[0] == "server":
                    headers = {"Authorization": f"Bearer {words[2]}"}
                    client = httpx.AsyncClient(base_url=words[1], headers=headers, timeout=10)
                    # Connected before the first stop, as an HMI's page is: the first
                    # request of a client (its connection, httpx's own first-use set-up)
                    # took 15 ms more, charged to the first stop of every run.
                    (await client.get("/state")).raise_for_status()
                    print("ready", flush=True)
                elif words[0] == "arm":
                    robot.last_stop_at = None
                    glue.close_commanded_at = None
                    print("armed", flush=True)
                elif words[0] == "stamps":
                    print(await stamps(robot, glue), flush=True)
                elif words[0] == "fire" and client is not None:
                    print(await fire(client, robot, glue), flush=True)
        finally:
            if client is not None:
                await client.aclose()


if __name__ == "__main__":
    asyncio.run(witness(float(sys.argv[1]) if len(sys.argv) > 1 else 3.0))
