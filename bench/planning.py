"""GET /workpieces while the worst part the library accepts is planned and cancelled.

A part with an 800-point outline and a 1 mm fill takes minutes to plan; left
running after each cancel, such plans would starve GET /workpieces and
/history. So the library refuses such a part at edit, a planning stops at
cancel or at planning_timeout, and it runs on a thread of its own. This
measures what that leaves:

- in this process: how long the worst part the library accepts takes to plan
  (`plan_path`, --repeats times), which is what the limits and the
  planning_timeout default were chosen from (docs/operations-guide.md);
- against the production server (`python -m server`, simulators on loopback,
  in its own process): the latency of GET /workpieces, one request after
  another, while idle; while that worst part is started and cancelled
  mid-plan, --cycles times; while the demo part (which plans in milliseconds)
  is started and cancelled the same way, the control: what the start and
  cancel cost by themselves; and while that 800-point part (stored as a file
  written before the limits, which the server still reads) is started and
  cancelled the same way. For each, how long a cancel took to bring the cell
  back to IDLE (the planning has stopped by then) and the server's RSS.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import math
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import psutil
from pydantic import ValidationError

from bench.report import emit, percentiles_ms
from server.core.operations.trajectory import plan_path
from server.core.operations.workpieces import Target
from server.settings.model import Settings
from server.storage.files import write_json_atomic
from server.storage.workpieces import (
    MAX_OUTLINE_POINTS,
    SpraySettings,
    Workpiece,
    WorkpieceIn,
)
from server.vision.paths import fill_size
from tests.processes import ROOT, _env, wait_answering
from tests.serving import admin_headers, free_port

SPEED_FACTOR = "20"  # the simulated robot's moves (the warm-up, the homing) go 20× faster


def comb(teeth: int) -> list[tuple[float, float]]:
    """A 700 × 700 mm comb inside the default workspace: a straight bottom edge and a
    sawtooth top of `teeth` teeth, 2 × teeth + 1 points. Each scan line crosses every tooth,
    and zigzag joins are tested against every edge: the most work per point allowed."""
    xs = np.linspace(0.0, 700.0, 2 * teeth + 1)
    top = [(float(x), 700.0 if i % 2 else 210.0) for i, x in enumerate(xs)]
    return [(x + 100.0, y - 350.0) for x, y in [(0.0, 0.0), (700.0, 0.0), *top[::-1]]]


def gear(points: int = 800, radius: float = 300.0) -> list[tuple[float, float]]:
    """The issue's outline: `points` points, teeth 15 % deep, centred at (450, 0) mm."""
    t = np.linspace(0.0, 2 * math.pi, points, endpoint=False)
    r = radius * (1 + 0.15 * np.where(np.arange(points) % 2 == 0, 1.0, -1.0))
    return [
        (450.0 + float(a * math.cos(b)), float(a * math.sin(b))) for a, b in zip(r, t, strict=True)
    ]


def accepted(outline: list[tuple[float, float]], spacing: float) -> bool:
    try:
        WorkpieceIn(
            name="w", outline_mm=outline, spray={"fill": "zigzag", "fill_spacing_mm": spacing}
        )
    except ValidationError:
        return False
    return True


def worst_allowed_part() -> dict[str, Any]:
    """The comb with the most teeth the point limit allows, at the finest accepted spacing
    (0.25 mm steps)."""
    outline = comb((MAX_OUTLINE_POINTS - 3) // 2)
    low, high = 4, 800  # quarter millimetres: 1 mm refused, 200 mm accepted
    while high - low > 1:
        middle = (low + high) // 2
        low, high = (low, middle) if accepted(outline, middle / 4) else (middle, high)
    spacing = high / 4
    lines, strokes = fill_size(np.asarray(outline), spacing, max_lines=10**6)
    return {
        "name": "worst allowed",
        "outline_mm": outline,
        "spray": {"fill": "zigzag", "fill_spacing_mm": spacing},
        "points": len(outline),
        "fill_lines": lines,
        "fill_strokes": strokes,
    }


def plan_seconds(part: dict[str, Any], repeats: int) -> list[float]:
    target = Target(
        "worst", "worst", np.asarray(part["outline_mm"]), SpraySettings(**part["spray"])
    )
    took = []
    for _ in range(repeats):
        started = time.perf_counter()
        plan_path([target], Settings())
        took.append(time.perf_counter() - started)
    return took


@contextlib.contextmanager
def production_server(data_dir: Path, port: int) -> Iterator[subprocess.Popen[str]]:
    env = _env({"GLUE_APP_SIMULATION_SPEED_FACTOR": SPEED_FACTOR})
    with (data_dir / "server.log").open("w") as log:
        process = subprocess.Popen(
            [sys.executable, "-m", "server", "--port", str(port), "--data-dir", str(data_dir)],
            stdout=log,
            stderr=subprocess.STDOUT,
            text=True,
            env=env,
            cwd=ROOT,
        )
        try:
            wait_answering(process, f"http://127.0.0.1:{port}/health", 120)
            yield process
        finally:
            process.terminate()
            try:
                process.wait(30)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(5)


async def wait_state(api: httpx.AsyncClient, wanted: str) -> None:
    async with asyncio.timeout(120):
        while (await api.get("/state")).json()["state"] != wanted:
            await asyncio.sleep(0.01)


async def probe(api: httpx.AsyncClient, done: asyncio.Event, interval: float) -> list[float]:
    """GET /workpieces one after another until `done`; each request's duration."""
    samples = []
    while not done.is_set():
        started = time.perf_counter()
        response = await api.get("/workpieces")
        samples.append(time.perf_counter() - started)
        response.raise_for_status()
        await asyncio.sleep(interval)
    return samples


async def start_and_cancel(
    api: httpx.AsyncClient, workpiece_id: str, cycles: int, cancel_after: float
) -> list[float]:
    """Start a run of `workpiece_id` as stored, cancel it mid-plan; seconds cancel → IDLE."""
    took = []
    body = {"contour_matching": False, "workpiece_id": workpiece_id}
    for _ in range(cycles):
        answer = await api.post("/start", json=body)
        assert answer.status_code == 202, answer.text
        await asyncio.sleep(cancel_after)
        started = time.perf_counter()
        answer = await api.post("/cancel")
        assert answer.status_code == 202, answer.text
        await wait_state(api, "IDLE")
        took.append(time.perf_counter() - started)
    return took


async def condition(
    api: httpx.AsyncClient,
    name: str,
    process: psutil.Process,
    args: argparse.Namespace,
    workpiece_id: str | None,
) -> dict[str, Any]:
    done = asyncio.Event()
    probing = asyncio.create_task(probe(api, done, args.interval))
    cancels: list[float] = []
    if workpiece_id is None:
        await asyncio.sleep(args.idle)
    else:
        cancels = await start_and_cancel(api, workpiece_id, args.cycles, args.cancel_after)
    done.set()
    samples = await probing
    row: dict[str, Any] = {"condition": name, **percentiles_ms(samples)}
    if cancels:
        row["cycles"] = len(cancels)
        row["cancel_to_idle_p50_ms"] = round(statistics.median(cancels) * 1000, 1)
        row["cancel_to_idle_max_ms"] = round(max(cancels) * 1000, 1)
    row["server_rss_mb"] = round(process.memory_info().rss / 2**20, 1)
    return row


async def against_server(
    args: argparse.Namespace, data_dir: Path, port: int, worst: dict[str, Any], pid: int
) -> list[dict[str, Any]]:
    process = psutil.Process(pid)
    headers = admin_headers(data_dir)
    async with httpx.AsyncClient(
        base_url=f"http://127.0.0.1:{port}", headers=headers, timeout=60
    ) as api:
        await wait_state(api, "IDLE")
        body = {k: worst[k] for k in ("name", "outline_mm", "spray")}
        assert (await api.put("/workpieces/worst", json=body)).status_code == 200
        issue = Workpiece(
            id="issue",
            name="the issue's part",
            outline_mm=gear(),
            spray=SpraySettings(fill="zigzag", fill_spacing_mm=1.0),
            created_at=time.time(),
            updated_at=time.time(),
        )  # as stored before the limits: the library reads it, an edit would be refused
        write_json_atomic(data_dir / "workpieces" / "issue.json", issue.model_dump(mode="json"))
        assert (await api.post("/home")).status_code == 202
        await asyncio.sleep(2.0)  # the robot reaches its safe position: runs start there
        rows = [await condition(api, "idle", process, args, None)]
        rows.append(
            await condition(
                api, "control: demo part (plans in ms), cancelled", process, args, "demo"
            )
        )
        rows.append(
            await condition(api, "worst allowed part planned, cancelled", process, args, "worst")
        )
        rows.append(
            await condition(
                api, "issue's part (stored before the limits), cancelled", process, args, "issue"
            )
        )
    return rows


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--repeats", type=int, default=5, help="in-process plans of the worst part")
    parser.add_argument("--cycles", type=int, default=30, help="start/cancel cycles per condition")
    parser.add_argument("--cancel-after", type=float, default=0.3, help="seconds after start")
    parser.add_argument("--idle", type=float, default=10.0, help="seconds measured while idle")
    parser.add_argument("--interval", type=float, default=0.01, help="seconds between GETs")
    args = parser.parse_args(argv)
    worst = worst_allowed_part()
    planned = plan_seconds(worst, args.repeats)
    with tempfile.TemporaryDirectory(prefix="bench-planning-") as tmp:
        data_dir, port = Path(tmp), free_port()
        with production_server(data_dir, port) as server:
            rows = asyncio.run(against_server(args, data_dir, port, worst, server.pid))
    extra = {
        "worst_allowed_part": {
            "points": worst["points"],
            "fill": "zigzag",
            "fill_spacing_mm": worst["spray"]["fill_spacing_mm"],
            "fill_lines": worst["fill_lines"],
            "fill_strokes": worst["fill_strokes"],
            "plan_s_median": round(statistics.median(planned), 3),
            "plan_s_max": round(max(planned), 3),
            "repeats": len(planned),
        },
        "planning_timeout_default_s": Settings().planning_timeout,
        "cycles": args.cycles,
        "cancel_after_s": args.cancel_after,
        "interval_s": args.interval,
    }
    print(
        f"\nworst allowed part: {worst['points']} points, zigzag at "
        f"{worst['spray']['fill_spacing_mm']} mm ({worst['fill_lines']} lines, "
        f"{worst['fill_strokes']} strokes): plans in {statistics.median(planned):.2f} s "
        f"(median of {len(planned)}, max {max(planned):.2f} s)"
    )
    emit("planning", rows, extra)
    return rows


if __name__ == "__main__":
    main()
