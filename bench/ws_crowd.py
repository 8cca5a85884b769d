"""A crowd of WebSocket clients that connect to /ws and read everything, in their own process.

`python -m bench.ws_crowd --url ws://127.0.0.1:8000/ws --clients 1000` (the
bearer token in the GLUE_BENCH_TOKEN environment variable) prints
"connected N" once every client is connected, then keeps reading until its
standard input closes, and prints "received M messages, K closed" before it
exits. Benchmarks use it to load the server's fan-out with live dashboards
without sharing their own process, or their core's time slices, with them.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import resource
import sys

import websockets


async def crowd(url: str, clients: int, token: str) -> None:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, min(hard, clients + 256)), hard))
    headers = {"Authorization": f"Bearer {token}"}
    sockets = []
    for _ in range(clients):  # one by one: a burst of handshakes is not what is measured
        sockets.append(await websockets.connect(url, additional_headers=headers, max_size=None))
    received = 0
    closed = 0

    async def read(socket: websockets.ClientConnection) -> None:
        nonlocal received, closed
        try:
            async for _ in socket:
                received += 1
        except websockets.ConnectionClosed:
            pass
        closed += 1

    readers = [asyncio.create_task(read(socket)) for socket in sockets]
    print(f"connected {len(sockets)}", flush=True)
    await asyncio.to_thread(sys.stdin.read)  # until the parent closes our stdin
    for socket in sockets:
        await socket.close()
    await asyncio.gather(*readers)
    print(f"received {received} messages, {closed} closed", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--url", required=True)
    parser.add_argument("--clients", type=int, default=1000)
    args = parser.parse_args()
    asyncio.run(crowd(args.url, args.clients, os.environ["GLUE_BENCH_TOKEN"]))


if __name__ == "__main__":
    main()
