"""The e-stop's answer while the HTTP port is attacked, against the quiet figure of the same run.

What is measured: POST /estop (the admin token, kept-alive connection from
127.0.0.1, as an HMI holds its own) from leaving the client to its answer
read, `--trials` times quiet, then `--trials` times while an attacker in a
process of its own runs:

- `--slow-clients` (1000) slow clients, spread over `--slow-addresses` (20)
  loopback addresses (127.0.1.x), each sending a request line and then one
  header line every `--header-every` (2) seconds, and connecting again (after
  0.5 s) when the server closes it, as a slowloris tool does;
- a bad-token flood: `--flood-connections` (8) keep-alive connections from
  127.0.2.1 sending GET /state with a wrong token as fast as they are answered
  (after auth_failure_limit of them, 429s).

The server is the production entry point, `python -m server`, on the
simulated cell, in its own process, with its default settings
(http_header_timeout 10 s, http_max_connections 512, 64 per address,
auth_failure_limit 20 per 60 s): the slow clients are more than it holds, so
it closes the oldest still waiting for headers for each new one
(server/api/connection_guard.py). The cell is stopped by the first e-stop
and stays in ERROR: each later one still halts the devices, posts
EMERGENCY_STOP and is answered once its journal commit is on disk.

Also reported: the attack's own counts (slow connections made and closed by
the server, flood answers by status) and the server's open file descriptors,
quiet and the most seen under attack (psutil), which the bound holds.

No timing is promised: on a shared machine the figures measure the machine
as much as the server. `python -m bench.estop_under_attack --help`.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import random
import resource
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import httpx
import psutil

from bench.report import emit, percentiles_ms
from bench.rest_throughput import spawned
from tests.processes import ROOT
from tests.serving import admin_headers, free_port

WRONG_TOKEN = "gc_00000000_notthetokennotthetokennot"
RECONNECT_S = 0.5  # a slow client closed by the server connects again after this


def stops(port: int, headers: dict[str, str], trials: int) -> tuple[list[float], Counter[int]]:
    """`trials` e-stops on one kept-alive connection; their round trips and statuses."""
    samples: list[float] = []
    statuses: Counter[int] = Counter()
    with httpx.Client(base_url=f"http://127.0.0.1:{port}", headers=headers, timeout=30) as client:
        for _ in range(trials):
            started = time.perf_counter()
            answer = client.post("/estop", json={"reason": "bench"})
            samples.append(time.perf_counter() - started)
            statuses[answer.status_code] += 1
            time.sleep(random.uniform(0.01, 0.03))
    return samples, statuses


# --- the attacker's process ----------------------------------------------------------


async def slow_client(
    address: str, port: int, every: float, counts: Counter[str], stop: asyncio.Event
) -> None:
    """One slow client for the attack's whole length: reconnects whenever it is closed."""
    while not stop.is_set():
        try:
            reader, writer = await asyncio.open_connection(
                "127.0.0.1", port, local_addr=(address, 0)
            )
        except OSError:
            counts["connect_failed"] += 1
            await asyncio.sleep(RECONNECT_S)
            continue
        counts["connections"] += 1
        try:
            writer.write(b"GET /state HTTP/1.1\r\nHost: cell\r\n")
            line = 0
            while not stop.is_set():
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(reader.read(4096), every)
                    counts["closed_by_server"] += 1  # an answer (408/503) or the end
                    break
                line += 1
                writer.write(b"X-Slow-%d: still coming\r\n" % line)
                await writer.drain()
        except OSError:
            counts["closed_by_server"] += 1
        finally:
            writer.close()
        await asyncio.sleep(RECONNECT_S)


async def flood(port: int, statuses: Counter[int], stop: asyncio.Event) -> None:
    """Wrong tokens, one request after another's answer, on a kept-alive connection."""
    request = (
        f"GET /state HTTP/1.1\r\nHost: cell\r\nAuthorization: Bearer {WRONG_TOKEN}\r\n\r\n"
    ).encode()
    while not stop.is_set():
        try:
            reader, writer = await asyncio.open_connection(
                "127.0.0.1", port, local_addr=("127.0.2.1", 0)
            )
        except OSError:
            await asyncio.sleep(0.1)
            continue
        try:
            while not stop.is_set():
                writer.write(request)
                head = await reader.readuntil(b"\r\n\r\n")
                length = 0
                for header in head.split(b"\r\n"):
                    if header[:15].lower() == b"content-length:":
                        length = int(header[15:])
                await reader.readexactly(length)
                statuses[int(head[9:12])] += 1
        except (OSError, asyncio.IncompleteReadError):
            statuses[0] += 1  # closed under it
        finally:
            writer.close()


async def attack(args: argparse.Namespace) -> dict[str, Any]:
    """Run the attack until stdin closes; what it did."""
    _, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
    stop = asyncio.Event()
    counts: Counter[str] = Counter()
    statuses: Counter[int] = Counter()
    tasks = []
    for n in range(args.slow_clients):
        address = f"127.0.1.{n % args.slow_addresses + 1}"
        tasks.append(
            asyncio.create_task(slow_client(address, args.port, args.header_every, counts, stop))
        )
        if n % 50 == 49:
            await asyncio.sleep(0.01)  # let the connections be made
    tasks += [
        asyncio.create_task(flood(args.port, statuses, stop)) for _ in range(args.flood_connections)
    ]
    while counts["connections"] < args.slow_clients:
        await asyncio.sleep(0.05)
    print("ready", flush=True)
    await asyncio.get_running_loop().run_in_executor(None, sys.stdin.read)  # until closed
    stop.set()
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    return {
        "slow_connections_made": counts["connections"],
        "slow_closed_by_server": counts["closed_by_server"],
        "slow_connect_failed": counts["connect_failed"],
        "flood_answers": {str(status): n for status, n in sorted(statuses.items())},
    }


# --- the run -----------------------------------------------------------------------


def run(args: argparse.Namespace) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    with tempfile.TemporaryDirectory() as scratch:
        data = Path(scratch)
        port = free_port()
        with spawned(["-m", "server"], port, data, "/health") as server:
            headers = admin_headers(data)
            process = psutil.Process(server.pid)
            fds_quiet = process.num_fds()
            quiet, quiet_statuses = stops(port, headers, args.trials)
            attacker = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "bench.estop_under_attack",
                    "--attacker",
                    "--port",
                    str(port),
                    "--slow-clients",
                    str(args.slow_clients),
                    "--slow-addresses",
                    str(args.slow_addresses),
                    "--flood-connections",
                    str(args.flood_connections),
                    "--header-every",
                    str(args.header_every),
                ],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                text=True,
                cwd=ROOT,
            )
            assert attacker.stdin is not None and attacker.stdout is not None
            try:
                if attacker.stdout.readline().strip() != "ready":
                    raise RuntimeError("the attacker did not start")
                time.sleep(args.settle)
                fds_most = [process.num_fds()]
                sampling = threading.Event()

                def sample() -> None:
                    while not sampling.wait(0.2):
                        fds_most.append(process.num_fds())

                sampler = threading.Thread(target=sample, daemon=True)
                sampler.start()
                attacked, attacked_statuses = stops(port, headers, args.trials)
                sampling.set()
                sampler.join()
                attacker.stdin.close()
                report = json.loads(attacker.stdout.readline())
            finally:
                if attacker.poll() is None:
                    attacker.send_signal(signal.SIGTERM)
                attacker.wait(30)
    condition = (
        f"{args.slow_clients} slow clients + bad-token flood ({args.flood_connections} connections)"
    )
    rows = [
        {"condition": "quiet", **percentiles_ms(quiet), "not_202": _not_202(quiet_statuses)},
        {
            "condition": condition,
            **percentiles_ms(attacked),
            "not_202": _not_202(attacked_statuses),
        },
    ]
    extra = {
        "attack": report,
        "server_open_fds": {"quiet": fds_quiet, "attacked_max": max(fds_most)},
        "server_settings": "defaults: http_header_timeout 10 s, http_max_connections 512 "
        "(64 per address), auth_failure_limit 20 per 60 s, lockout 60 s",
        "note": "a shared two-core machine: the server, the attacker and the e-stop client "
        "take turns on the same cores",
    }
    return rows, extra


def _not_202(statuses: Counter[int]) -> int:
    return sum(n for status, n in statuses.items() if status != 202)


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--trials", type=int, default=300, help="e-stops per condition")
    parser.add_argument("--slow-clients", type=int, default=1000)
    parser.add_argument("--slow-addresses", type=int, default=20, help="at most 254")
    parser.add_argument("--flood-connections", type=int, default=8)
    parser.add_argument("--header-every", type=float, default=2.0, help="seconds between lines")
    parser.add_argument("--settle", type=float, default=3.0, help="seconds of attack before")
    parser.add_argument("--attacker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--port", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.attacker:
        print(json.dumps(asyncio.run(attack(args))), flush=True)
        return []
    rows, extra = run(args)
    emit("estop_under_attack", rows, extra)
    return rows


if __name__ == "__main__":
    main()
