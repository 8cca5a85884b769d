"""A simulator run as a process of its own (`python -m server.drivers.sim.<name>`)."""

from __future__ import annotations

import asyncio
import signal


def stopped_by_signals() -> asyncio.Event:
    """An event that SIGTERM or SIGINT sets: how a simulator's process is told to stop
    (its sockets then closed in order). Call it inside the running loop."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    return stop
