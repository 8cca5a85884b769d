"""A simulator run as a process of its own (`python -m server.drivers.sim.<name>`)."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import signal
from collections.abc import Callable, Coroutine, Sequence
from typing import Any, Protocol


class Served(Protocol):
    """A simulator's server once started: where it listens, and how it stops."""

    @property
    def host(self) -> str: ...

    @property
    def port(self) -> int: ...

    async def stop(self) -> None: ...


def stopped_by_signals() -> asyncio.Event:
    """An event that SIGTERM or SIGINT sets: how a simulator's process is told to stop
    (its sockets then closed in order). Call it inside the running loop."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    return stop


async def serve_until_signalled(
    server: Served, name: str, stop: asyncio.Event | None = None
) -> None:
    """Say "`name` listening on HOST:PORT" (the line tests/processes.py: simulator waits
    for), serve until SIGTERM or SIGINT (`stop`, if armed before the start), then stop."""
    stop = stop if stop is not None else stopped_by_signals()
    print(f"{name} listening on {server.host}:{server.port}", flush=True)
    try:
        await stop.wait()
    finally:
        await server.stop()


def simulator_arguments(description: str, port: int) -> argparse.ArgumentParser:
    """The options every simulator takes: --host, --port (0 picks a free one), --log-level."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=port, help="0 picks a free port")
    parser.add_argument("--log-level", default="WARNING")
    return parser


def run_standalone(
    run: Callable[[argparse.Namespace], Coroutine[Any, Any, None]],
    parser: argparse.ArgumentParser,
    argv: Sequence[str] | None,
) -> None:
    """Parse `argv`, set the log level, and run `run(args)` until it returns or Ctrl-C."""
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(message)s"
    )
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(run(args))
