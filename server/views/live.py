"""The live device feed: valve, flow, pressure and the robot's position on the bus.

Why a feed and not the 3 s poll of GET /health the dashboard used: a valve
opened and closed between two polls was never seen, and "valve closed" showed
while glue flowed. The feed publishes a `device` message

* every `device_push_interval` (0.1 s) while an operation runs, and
  IDLE_PUSH_S (1 s) otherwise, so a page sees links come and go without polling;
* at once after every change of state, so the valve state read back by a
  stop's close (`ModbusGlueDispenser` keeps it in its health) shows right away.

It reads what the drivers already keep (`CellDevices.health()`): the dispenser
polls its status every glue_poll_interval. The robot's pose is read only by its
moves and heartbeat, so while an operation runs the feed asks for it whenever
the last read is older than one push interval, one request at a time, waiting
half an interval at most for the answer: `getPosition` reads, it never moves. Each value carries its
age (`age_ms`), so a client can tell how fresh it is.

A `device` message is a bus sample (server/core/infra/bus.py): no seq, not replayed,
sent only to /ws clients that ask for the type. Publishing never waits (the bus
is non-blocking) and the feed is a task of its own, so nothing here can delay
the worker. The feed is composed by the Cell,
not the worker: the core's unit tests count the worker's messages exactly.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable
from typing import Any

from server.core.infra.bus import Bus, Subscription, SubscriptionClosed
from server.core.machine.transitions import OPERATIONAL_STATES
from server.core.worker.devices import CellDevices
from server.core.worker.view import CellView

log = logging.getLogger(__name__)

IDLE_PUSH_S = 1.0  # outside operations: link state without polling, few messages
GLUE_FIELDS = (
    "connected",
    "valve_open",
    "flow_ml_min",
    "flow_setpoint_ml_min",
    "pressure_psi",
    "pressure_setpoint_psi",
    "temperature_c",
    "alarms",
    "active_faults",
)
ROBOT_FIELDS = ("connected", "position")


def device_message(health: dict[str, dict[str, Any]], now: float) -> dict[str, Any]:
    """The `device` message's payload from `CellDevices.health()` at Unix time `now`.

    Pure, so its shape is tested without a loop. `age_ms` is how old the
    reading is (None before the first one).
    """

    def part(name: str, fields: tuple[str, ...], stamp: str) -> dict[str, Any]:
        device = health.get(name, {})
        taken = device.get(stamp)
        age = None if taken is None else round(max(0.0, now - taken) * 1000.0, 1)
        return {**{f: device.get(f) for f in fields}, "age_ms": age}

    return {
        "glue": part("glue", GLUE_FIELDS, "status_at"),
        "robot": part("robot", ROBOT_FIELDS, "position_at"),
    }


class DeviceFeed:
    """Publishes `device` messages (see the module docstring); start() and stop()."""

    def __init__(self, devices: CellDevices, bus: Bus, view: CellView, interval: float) -> None:
        self.devices = devices
        self.bus = bus
        self.view = view
        self.interval = interval
        self._task: asyncio.Task[None] | None = None
        self._asking: asyncio.Task[None] | None = None
        # Told of each message published, with its time (the flight recorder): called on
        # the feed's task, so a listener must not block.
        self.listeners: list[Callable[[dict[str, Any], float], None]] = []

    def start(self) -> None:
        if self._task is None:
            self._task = asyncio.create_task(self._run(), name="device-feed")

    async def stop(self) -> None:
        tasks = {t for t in (self._task, self._asking) if t is not None}
        self._task = self._asking = None
        for task in tasks:
            task.cancel()
        if tasks:
            await asyncio.wait(tasks)

    def publish(self) -> None:
        """Push one `device` message now."""
        now = time.time()
        message = device_message(self.devices.health(), now)
        self.bus.publish_sample("device", message)
        for listener in self.listeners:
            try:
                listener(message, now)
            except Exception:  # a listener's bug must not stop the live feed
                log.exception("a device feed listener failed")

    async def _run(self) -> None:
        subscription = self._subscribe()
        while True:
            running = self.view.state in OPERATIONAL_STATES
            if running:
                await self._refresh_position()
            self.publish()
            try:
                async with asyncio.timeout(self.interval if running else IDLE_PUSH_S):
                    await subscription.get()  # a change of state: push at once
            except TimeoutError:
                pass
            except SubscriptionClosed:  # fell behind (a stalled loop): start afresh
                subscription = self._subscribe()

    def _subscribe(self) -> Subscription:
        return self.bus.subscribe(64, types=["state_changed"])

    async def _refresh_position(self) -> None:
        """Ask the robot for its pose when the last one read is older than a push interval.

        The answer is awaited for half an interval at most (a round trip is well
        under a millisecond): the message then carries the fresh pose, and a robot
        that does not answer delays no message by more than that.
        """
        asking = self._asking
        if asking is None or asking.done():
            taken = self.devices.robot.health.details.get("position_at")
            if taken is not None and time.time() - taken < self.interval:
                return  # a move's own read is fresh enough
            if not self.devices.robot.health.connected:
                return
            asking = self._asking = asyncio.create_task(
                self._ask_position(), name="device-feed-position"
            )
        await asyncio.wait({asking}, timeout=self.interval / 2)

    async def _ask_position(self) -> None:
        # A failure here is the robot driver's to report (link lost, no answer); the
        # feed only shows the age of the last pose it has.
        with contextlib.suppress(Exception):
            await self.devices.robot.get_position()
