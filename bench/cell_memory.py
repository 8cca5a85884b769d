"""Unique memory of every process of a running cell, after start and after runs.

`python -m server` is started as a plant starts it, on a fresh data directory
(the simulated cell commissions itself), and sprays the demo part `--runs`
times over HTTP (POST /start, then GET /state until IDLE). After start-up,
after the first run and after the last, every process of the cell is read from
/proc/<pid>/smaps_rollup (through psutil):

- unique (USS, Private_Clean + Private_Dirty): what the process alone holds,
  freed when it ends; the figure the goals are set on;
- PSS: its share of what it shares (libraries, the frames' shared memory);
- RSS: all it has mapped, shared or not.

Two layouts: `sim`, the default run (simulators on loopback in the server's own
process, the simulated camera rendering in the image process), and `devices`,
every device a process of its own, the server pointed at each by address as at
real devices: the robot and glue simulators (ROBOT_IP, GLUE_CONTROLLER_PORT) and
a network camera (VISION_CAMERA_ID, an MJPEG stream over HTTP from
`server.drivers.sim.camera_stream`, read through OpenCV's video I/O as a real
one is). Their own memory is listed apart and not counted in the cell's total.
A cell with a real camera does not commission itself: the `devices` data
directory is commissioned first by the same server on the simulated camera,
which the stream's table matches, then the server starts again on the stream.
Its runs are inspected against a frame without the bead (the stream does not
know what the robot laid): the parts are judged defective, as nothing here
reads.

The processes are found by walking the server's descendants: the image process
(`multiprocessing.spawn`), multiprocessing's resource tracker.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import psutil

from server.settings.calibration import CalibrationSettings
from tests.processes import server_process, simulator
from tests.serving import free_port

SPEED_FACTOR = "20"  # the simulated robot's moves go this many times faster: a run in seconds
# A frame's bound, not a figure: the image process works below the server's priority, and
# on a machine busy with other work a frame (even the camera's first answer) can wait seconds.
CAMERA_TIMEOUT_S = "30"
RUN_TIMEOUT_S = 300.0  # a bound on one run, never a performance assertion
CAMERA_SETTING = "VISION_CAMERA_ID"  # the camera's address (an OpenCV index or URL)


def role_of(process: psutil.Process, server_pid: int) -> str:
    """What a process of the cell is, from its command line."""
    if process.pid == server_pid:
        return "server"
    line = " ".join(process.cmdline())
    if "resource_tracker" in line:
        return "resource tracker"
    if "multiprocessing.spawn" in line:
        return "image process"
    if "robot_sim" in line:
        return "robot simulator"
    if "glue_sim" in line:
        return "glue simulator"
    return line[:60]


def process_memory(pid: int) -> dict[str, float]:
    """Unique, proportional and resident memory of one process, in MB."""
    info = psutil.Process(pid).memory_full_info()
    return {
        "unique_mb": round(info.uss / 2**20, 1),
        "pss_mb": round(info.pss / 2**20, 1),
        "rss_mb": round(info.rss / 2**20, 1),
    }


def cell_processes(server_pid: int) -> list[psutil.Process]:
    server = psutil.Process(server_pid)
    return [server, *server.children(recursive=True)]


def measure_point(point: str, server_pid: int, others: dict[str, int]) -> list[dict[str, Any]]:
    """One row per process of the cell, one per process outside it, and the cell's total."""
    rows = []
    for process in cell_processes(server_pid):
        with contextlib.suppress(psutil.NoSuchProcess):
            rows.append(
                {"point": point, "process": role_of(process, server_pid), "pid": process.pid}
                | process_memory(process.pid)
            )
    total = {
        "point": point,
        "process": "cell total",
        "unique_mb": round(sum(row["unique_mb"] for row in rows), 1),
        "pss_mb": round(sum(row["pss_mb"] for row in rows), 1),
        "rss_mb": round(sum(row["rss_mb"] for row in rows), 1),
    }
    for name, pid in others.items():
        rows.append({"point": point, "process": f"{name} (not counted)", "pid": pid})
        rows[-1].update(process_memory(pid))
    return [*rows, total]


def admin(port: int, data: Path) -> httpx.Client:
    token = (data / "admin.token").read_text().strip()
    return httpx.Client(
        base_url=f"http://127.0.0.1:{port}",
        headers={"Authorization": f"Bearer {token}"},
        timeout=30,
    )


def wait_state(api: httpx.Client, wanted: str, timeout: float = RUN_TIMEOUT_S) -> None:
    deadline = time.monotonic() + timeout
    while True:
        state = api.get("/state").json()
        if state["state"] == wanted:
            return
        if state["state"] == "ERROR" or time.monotonic() > deadline:
            reason = state.get("stop_reason")
            raise RuntimeError(f"the cell is {state['state']}, not {wanted}: {reason}")
        time.sleep(0.05)


def require_commissioned(data: Path) -> None:
    """RuntimeError if the cell started without its demo part: every start
    would then be refused as "the workpiece library is empty" (its commissioning failed)."""
    if not any((data / "workpieces").glob("*.json")):
        raise RuntimeError("the simulated cell did not commission itself (a frame late?)")


def one_run(api: httpx.Client) -> str | None:
    """One spray run to its end: None, or the code of the fault that stopped it (the cell
    is then reset, as a person would, and the next run goes on: on a machine shared with
    other work a frame can miss its timeout)."""
    deadline = time.monotonic() + RUN_TIMEOUT_S
    while (answer := api.post("/start")).status_code == 409:  # the home move still under way
        if time.monotonic() > deadline:
            raise RuntimeError(f"the start is refused: {answer.json()}")
        time.sleep(0.2)
    answer.raise_for_status()
    run_id = answer.json()["run_id"]
    deadline = time.monotonic() + RUN_TIMEOUT_S
    while True:
        state = api.get("/state").json()
        if state["state"] == "IDLE" and (state.get("operation") or {}).get("run_id") != run_id:
            return None
        if state["state"] == "ERROR":  # reset, and the robot sent home, as a person would
            # A reset is refused (409) while the fault's own stop is still being made: asked
            # again, as a person presses Reset again.
            while (reset := api.post("/reset")).status_code == 409:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"the reset is refused: {reset.json()}")
                time.sleep(0.2)
            reset.raise_for_status()
            wait_state(api, "IDLE")
            api.post("/home").raise_for_status()
            return str((state.get("stop_reason") or {}).get("code"))
        if time.monotonic() > deadline:
            raise RuntimeError(f"run {run_id} did not end: {state}")
        time.sleep(0.05)


@contextlib.contextmanager
def devices_apart() -> Iterator[tuple[dict[str, str], dict[str, int]]]:
    """The robot, glue and camera simulators as processes of their own: the server's
    settings for them (the camera's under CAMERA_SETTING) and their pids."""
    with (
        simulator("server.drivers.sim.robot_sim", "--speed-factor", SPEED_FACTOR) as robot,
        simulator("server.drivers.sim.glue_sim", "--speed-factor", SPEED_FACTOR) as glue,
        simulator("server.drivers.sim.camera_stream") as camera,
    ):
        env = {
            "ROBOT_IP": "127.0.0.1",
            "GLUE_APP_ROBOT_PORT": str(robot.port),
            "GLUE_CONTROLLER_PORT": f"tcp://127.0.0.1:{glue.port}",
            CAMERA_SETTING: f"http://127.0.0.1:{camera.port}/stream.mjpg",
            # a real camera's table is set explicitly: the stream's is the simulated one
            "GLUE_APP_MARKER_POSITIONS_MM": json.dumps(CalibrationSettings().marker_positions_mm),
        }
        pids = {
            "robot simulator": robot.process.pid,
            "glue simulator": glue.process.pid,
            "camera stream": camera.process.pid,
        }
        yield env, pids


def commission(data: Path, env: dict[str, str]) -> None:
    """Commission `data` as the simulated cell does itself: the server once on the
    simulated camera, with the same devices otherwise, stopped once it is IDLE."""
    simulated = {name: value for name, value in env.items() if name != CAMERA_SETTING}
    port = free_port()
    with server_process(port, data, simulated, timeout=300), admin(port, data) as api:
        wait_state(api, "IDLE")
        require_commissioned(data)


def measure(
    layout: str, runs: int, soak_minutes: float = 0.0, every_minutes: float = 5.0
) -> list[dict[str, Any]]:
    """The rows of one layout: after start-up, after the first run, after the last; then,
    with `soak_minutes`, runs go on for that long, the cell measured every
    `every_minutes` (a soak: memory that levels off shows flat rows, a leak a slope)."""
    with contextlib.ExitStack() as stack:
        env = {
            "GLUE_APP_SIMULATION_SPEED_FACTOR": SPEED_FACTOR,
            "GLUE_APP_VISION_PROCESSING_TIMEOUT": CAMERA_TIMEOUT_S,
        }
        others: dict[str, int] = {}
        if layout == "devices":
            settings, others = stack.enter_context(devices_apart())
            env.update(settings)
        data = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-memory-")))
        port = free_port()
        (data / "data").mkdir()
        if layout == "devices":
            commission(data / "data", env)
        server = stack.enter_context(server_process(port, data / "data", env, timeout=300))
        api = stack.enter_context(admin(port, data / "data"))
        wait_state(api, "IDLE")
        require_commissioned(data / "data")
        rows = measure_point("started", server.pid, others)
        faults: list[str] = []
        for index in range(runs):
            if (fault := one_run(api)) is not None:
                faults.append(fault)
            if index == 0 and runs > 1:
                rows += measure_point("after 1 run", server.pid, others)
        rows += measure_point(f"after {runs} run{'s' * (runs != 1)}", server.pid, others)
        started = time.monotonic()
        done, next_point = runs, started + every_minutes * 60
        while soak_minutes and time.monotonic() - started < soak_minutes * 60:
            if (fault := one_run(api)) is not None:
                faults.append(fault)
            done += 1
            if time.monotonic() >= next_point:
                minutes = (time.monotonic() - started) / 60
                rows += measure_point(f"soak {minutes:.1f} min, {done} runs", server.pid, others)
                next_point += every_minutes * 60
    return [{"layout": layout} | row | {"runs_stopped": len(faults)} for row in rows]


def totals(rows: list[dict[str, Any]]) -> dict[str, float]:
    """The cell's unique total after the last run, per layout."""
    last: dict[str, float] = {}
    for row in rows:
        if row["process"] == "cell total":
            last[row["layout"]] = row["unique_mb"]
    return last


def environment_note() -> dict[str, Any]:
    return {"load_average": os.getloadavg(), "speed_factor": float(SPEED_FACTOR)}
