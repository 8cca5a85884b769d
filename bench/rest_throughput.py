"""REST throughput: GET /state against a bare FastAPI endpoint of the same size.

GET /state is what every HMI and supervisor polls. Its cost should be the
framework's, not the cell's: the target is at least 0.9 of the requests per
second of a bare FastAPI route returning a pre-built dict of the same JSON.

How:
- The cell: the production entry point, `python -m server`, in its own process,
  simulated devices, a fresh data directory, default settings. /state needs the
  viewer role (server/security/policy.py), so every request carries the admin
  bearer token: the measured cost includes the route lookup among all the
  cell's routes, the token check, the HTTP door (body-size limit, audit and
  metrics observers), building the snapshot and validating the response model.
- The body /state answers is read once; the bare app (`--serve-bare`) is a
  FastAPI app with one GET /state returning that very dict (same JSON size)
  and nothing else. It is served through the same entry point,
  server.__main__.main, with only create_app swapped, so uvicorn runs with the
  same arguments (loop, HTTP parser, logging configured the same way: the
  access log line of each request goes to the console and the log file in
  both) on the same host. The two run one after the other, one process each;
  the bare server gets the same Authorization header, which it ignores.
- Turns: both servers run side by side and are loaded one at a time, cell then
  bare, `--rounds` times; each row is that target's median round, and the JSON
  keeps every round.
- The load: this process, apart from the server, runs `--concurrency`
  keep-alive HTTP/1.1 connections over raw asyncio streams (uvloop when
  installed), each sending its next request when the previous answer is in.
  After `--warmup` seconds, requests completed in `--duration` seconds give the
  rate; their latencies give p50/p99/max. Any answer but 200 is counted as an
  error.
- Below the target (or with --profile always), the cell is loaded once more
  under cProfile and the JSON gets `cell_profile`: µs per request of the
  functions with the most own time, and of the cell's own code, cumulative.

What limits the measurement: a single uvicorn process serves on one core, and
on a small machine the load generator needs the other one (and shares it with
whatever else runs): each row reports the CPU seconds the server and the load
generator used, so a server short of 1 CPU-second per second says the client or
the machine, not the server, set the pace. Access logging to two sinks is part
of the production configuration and of both figures. `cpu_ratio_to_bare` is
the bare server's CPU time per request over the cell's, the median of the
rounds: the rate ratio two servers would show each on a core of its own, and
far steadier than the rate when other work shares the machine.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import pstats
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Coroutine, Iterator
from pathlib import Path
from typing import Any

import httpx
import psutil

from bench.report import emit, percentiles_ms
from tests.processes import ROOT, _env, wait_answering
from tests.serving import admin_headers, free_port

TARGET_RATIO = 0.9


def bare_app(body: dict[str, Any]) -> Any:
    """One GET /state returning `body` as it is: the framework's cost and nothing else."""
    from fastapi import FastAPI

    app = FastAPI()

    @app.get("/state")
    async def state() -> dict[str, Any]:
        return body

    return app


def serve_bare(body_file: Path, port: int, data_dir: Path) -> None:
    """Serve the bare app through the production entry point (same uvicorn arguments)."""
    import server.__main__ as entry

    body = json.loads(body_file.read_text(encoding="utf-8"))
    entry.create_app = lambda settings, **_: bare_app(body)  # type: ignore[assignment]
    entry.main(["--port", str(port), "--data-dir", str(data_dir)])


@contextlib.contextmanager
def spawned(
    command: list[str],
    port: int,
    data_dir: Path,
    ready_path: str,
    stop_signal: signal.Signals = signal.SIGTERM,
    ready_within: float = 60.0,
) -> Iterator[subprocess.Popen[str]]:
    """Run `python <command>` from the project root until GET `ready_path` answers 200
    (within `ready_within` seconds).

    Stopped with `stop_signal`: SIGINT for a server under cProfile, which writes
    its statistics on KeyboardInterrupt (uvicorn re-raises SIGTERM, which would not).
    """
    with (data_dir / "server.log").open("w") as log:
        process = subprocess.Popen(
            [sys.executable, *command, "--port", str(port), "--data-dir", str(data_dir)],
            stdout=log,
            stderr=subprocess.STDOUT,
            text=True,
            env=_env(None),
            cwd=ROOT,
        )
        try:
            wait_answering(process, f"http://127.0.0.1:{port}{ready_path}", ready_within)
            yield process
        finally:
            process.send_signal(stop_signal)
            try:
                process.wait(30)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(5)


def request_bytes(port: int, headers: dict[str, str]) -> bytes:
    lines = ["GET /state HTTP/1.1", f"Host: 127.0.0.1:{port}"]
    lines += [f"{name}: {value}" for name, value in headers.items()]
    return ("\r\n".join(lines) + "\r\n\r\n").encode("ascii")


async def one_connection(
    port: int, request: bytes, stop_at: float, samples: list[float], errors: list[int]
) -> None:
    """Keep-alive requests, one at a time, until `stop_at` (perf_counter)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        while time.perf_counter() < stop_at:
            started = time.perf_counter()
            writer.write(request)
            head = await reader.readuntil(b"\r\n\r\n")
            status = int(head[9:12])
            length = 0
            for line in head.split(b"\r\n"):
                if line[:15].lower() == b"content-length:":
                    length = int(line[15:])
            await reader.readexactly(length)
            samples.append(time.perf_counter() - started)
            if status != 200:
                errors.append(status)
    finally:
        writer.close()
        with contextlib.suppress(OSError):
            await writer.wait_closed()


async def load(
    port: int, headers: dict[str, str], concurrency: int, seconds: float
) -> tuple[list[float], list[int], float]:
    """Latencies and error statuses of `concurrency` connections for `seconds`; elapsed time."""
    request = request_bytes(port, headers)
    samples: list[float] = []
    errors: list[int] = []
    started = time.perf_counter()
    stop_at = started + seconds
    await asyncio.gather(
        *(one_connection(port, request, stop_at, samples, errors) for _ in range(concurrency))
    )
    return samples, errors, time.perf_counter() - started


def measure(
    target: str, port: int, pid: int, headers: dict[str, str], args: argparse.Namespace
) -> dict[str, Any]:
    run_loop(load(port, headers, args.concurrency, args.warmup))
    server = psutil.Process(pid)
    server_cpu, client_cpu = sum(server.cpu_times()[:2]), time.process_time()
    samples, errors, elapsed = run_loop(load(port, headers, args.concurrency, args.duration))
    return {
        "target": target,
        "requests": len(samples),
        "errors": len(errors),
        "req_per_s": round(len(samples) / elapsed, 1),
        **percentiles_ms(samples),
        "server_cpu_s": round(sum(server.cpu_times()[:2]) - server_cpu, 2),
        "server_cpu_us_per_request": round(
            (sum(server.cpu_times()[:2]) - server_cpu) / max(len(samples), 1) * 1e6, 1
        ),
        "client_cpu_s": round(time.process_time() - client_cpu, 2),
        "seconds": round(elapsed, 2),
    }


def run_loop(coroutine: Coroutine[Any, Any, Any]) -> Any:
    """Run in uvloop when it is installed (as uvicorn[standard] installs it): a cheaper client."""
    factory: Callable[[], asyncio.AbstractEventLoop] | None = None
    with contextlib.suppress(ImportError):
        import uvloop

        factory = uvloop.new_event_loop
    with asyncio.Runner(loop_factory=factory) as runner:
        return runner.run(coroutine)


def settled_state(port: int, headers: dict[str, str]) -> httpx.Response:
    """GET /state once the cell has left INITIALIZING."""
    deadline = time.monotonic() + 60
    while True:
        response = httpx.get(f"http://127.0.0.1:{port}/state", headers=headers, timeout=5)
        response.raise_for_status()
        if response.json()["state"] != "INITIALIZING":
            return response
        if time.monotonic() > deadline:
            raise RuntimeError("the cell did not leave INITIALIZING within 60 s")
        time.sleep(0.05)


CELL_COMMAND = ["-m", "server"]


def bare_command(body: dict[str, Any], data_dir: Path) -> list[str]:
    body_file = data_dir / "body.json"
    body_file.write_text(json.dumps(body), encoding="utf-8")
    return ["-m", "bench.rest_throughput", "--serve-bare", str(body_file)]


def run(args: argparse.Namespace) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """The cell and the bare app (with the body the cell answered), measured in turns.

    Both servers are up for the whole comparison and are loaded one at a time,
    cell then bare, `--rounds` times; each target's row is its median round.
    Why turns: on a small shared machine the rate drifts by more than the gap
    being measured from one minute to the next, so one run of each, one after
    the other, compared the machine's moods as much as the two servers.
    """
    with tempfile.TemporaryDirectory(prefix="bench-rest-") as tmp:
        cell_dir, bare_dir = Path(tmp, "cell"), Path(tmp, "bare")
        cell_dir.mkdir()
        bare_dir.mkdir()
        cell_port, bare_port = free_port(), free_port()
        with spawned(CELL_COMMAND, cell_port, cell_dir, "/health") as cell_process:
            headers = admin_headers(cell_dir)
            first = settled_state(cell_port, headers)
            bare_command_line = bare_command(first.json(), bare_dir)
            with spawned(bare_command_line, bare_port, bare_dir, "/state") as bare_process:
                bare_url = f"http://127.0.0.1:{bare_port}/state"
                bare_size = len(httpx.get(bare_url, headers=headers).content)
                cells, bares = [], []
                for _ in range(args.rounds):
                    cells.append(
                        measure("cell GET /state", cell_port, cell_process.pid, headers, args)
                    )
                    bares.append(
                        measure(
                            "bare FastAPI GET /state", bare_port, bare_process.pid, headers, args
                        )
                    )
    sizes = {
        "state_body_bytes": len(first.content),
        "bare_body_bytes": bare_size,
        "rounds": [
            {
                "cell_req_per_s": c["req_per_s"],
                "bare_req_per_s": b["req_per_s"],
                "cell_cpu_us": c["server_cpu_us_per_request"],
                "bare_cpu_us": b["server_cpu_us_per_request"],
            }
            for c, b in zip(cells, bares, strict=True)
        ],
    }
    return [_median_round(cells), _median_round(bares)], sizes


def _median_round(rounds: list[dict[str, Any]]) -> dict[str, Any]:
    ordered = sorted(rounds, key=lambda row: row["req_per_s"])
    return {**ordered[len(ordered) // 2], "rounds": len(rounds)}


def profile_cell(args: argparse.Namespace, top: int = 15) -> dict[str, Any]:
    """The cell under load again, under cProfile: where the time of one request goes.

    Of the functions run at least once per measured request: the `top` by own
    time, and the cell's own (server/...) by cumulative time, in µs per request
    (inflated by the profiler: compare them with each other and with the total).
    """
    with tempfile.TemporaryDirectory(prefix="bench-rest-profile-") as tmp:
        data_dir, stats_file = Path(tmp), Path(tmp, "cell.prof")
        command = ["-m", "cProfile", "-o", str(stats_file), *CELL_COMMAND]
        port = free_port()
        # cProfile slows the start (the cell commissions itself, frames drawn and matched)
        with spawned(command, port, data_dir, "/health", signal.SIGINT, 300.0) as process:
            headers = admin_headers(data_dir)
            settled_state(port, headers)
            requests = measure("profiled", port, process.pid, headers, args)["requests"]
        stats = pstats.Stats(str(stats_file)).stats  # type: ignore[attr-defined]
    entries = [
        (f"{_short(file)}:{line}({name})", own / requests * 1e6, cumulative / requests * 1e6)
        for (file, line, name), (_, calls, own, cumulative, _) in stats.items()
        if calls >= requests
    ]
    by_own = sorted(entries, key=lambda entry: -entry[1])[:top]
    ours = sorted((e for e in entries if e[0].startswith("server/")), key=lambda e: -e[2])
    return {
        "requests_profiled": requests,
        "total_us_per_request": round(max(e[2] for e in entries), 1),
        "top_own_us_per_request": {name: round(own, 1) for name, own, _ in by_own},
        "cell_code_cumulative_us_per_request": {name: round(cum, 1) for name, _, cum in ours},
    }


def _short(file: str) -> str:
    """A path from the package root (site-packages/… or the project's own)."""
    for marker in ("site-packages/", "/lib/python"):
        if marker in file:
            return file.split(marker, 1)[1]
    return str(Path(file).relative_to(ROOT)) if file.startswith(str(ROOT)) else file


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--concurrency", type=int, default=32, help="keep-alive connections")
    parser.add_argument("--duration", type=float, default=5.0, help="measured seconds per target")
    parser.add_argument("--warmup", type=float, default=1.0, help="unmeasured seconds first")
    parser.add_argument(
        "--rounds", type=int, default=5, help="turns of cell then bare; rows are the medians"
    )
    parser.add_argument(
        "--profile",
        choices=("auto", "always", "never"),
        default="auto",
        help="profile the cell under load after the comparison (auto: if below the target)",
    )
    parser.add_argument("--serve-bare", type=Path, metavar="BODY_JSON", help=argparse.SUPPRESS)
    parser.add_argument("--port", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--data-dir", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.serve_bare:
        serve_bare(args.serve_bare, args.port, args.data_dir)
        return []
    rows, sizes = run(args)
    ratio = rows[0]["req_per_s"] / rows[1]["req_per_s"] if rows[1]["req_per_s"] else 0.0
    rows[0]["ratio_to_bare"] = round(ratio, 3)
    # The same comparison in the servers' CPU per request, round by round: what the rate
    # ratio is when each server has its core to itself, and far steadier on a busy machine.
    rows[0]["cpu_ratio_to_bare"] = round(
        statistics.median(r["bare_cpu_us"] / r["cell_cpu_us"] for r in sizes["rounds"]), 3
    )
    extra: dict[str, Any] = {
        **sizes,
        "concurrency": args.concurrency,
        "duration_s": args.duration,
        "auth": "Authorization: Bearer <admin token> on every request (/state needs viewer)",
        "target": f"cell /state at least {TARGET_RATIO} of the bare endpoint",
    }
    if args.profile == "always" or (args.profile == "auto" and ratio < TARGET_RATIO):
        extra["cell_profile"] = profile = profile_cell(args)
        print("\nwhere a cell GET /state spends its time (cProfile, µs per request):")
        print(f"  {profile['total_us_per_request']:>8}  total")
        for heading in ("top_own_us_per_request", "cell_code_cumulative_us_per_request"):
            print(f"  {heading}:")
            for name, micros in profile[heading].items():
                print(f"  {micros:>8}  {name}")
    emit("rest_throughput", rows, extra)
    return rows


if __name__ == "__main__":
    main()
