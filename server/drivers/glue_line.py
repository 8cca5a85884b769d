"""The Modbus line of the glue dispenser: its client, who goes next on it, cancellations kept.

`serial_client` and `tcp_client` build the pymodbus client of each transport (the
same RTU frames, CRC included, on RS-485 or over TCP), each with `retries=0` so its
own retry loop can never stretch a call past the dispenser's `timeout`.

Modbus RTU carries one exchange at a time and the pymodbus client is not safe
for concurrent transactions, so the dispenser's exchanges take turns through
`LineArbiter`, which serves a valve close (URGENT) before queued commands
(COMMAND) and queued commands before monitor polls (POLL).
`cancel_requests` and `cancel_dropped` find a cancellation pymodbus swallowed
(see `cancel_dropped`), so the caller can raise it again.
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Callable

from pymodbus import FramerType
from pymodbus.client import AsyncModbusSerialClient, AsyncModbusTcpClient

from server.common.errors import DeviceError
from server.drivers import glue_registers as regs

DEVICE = "glue"

URGENT, COMMAND, POLL = 0, 1, 2  # line priorities: valve close, commands, monitor polls

ModbusClient = AsyncModbusTcpClient | AsyncModbusSerialClient


def serial_client(port: str, timeout: float) -> Callable[[], ModbusClient]:
    """What builds the client of an RS-485 adapter (115200 baud, 8N1, Modbus RTU)."""

    def make_client() -> ModbusClient:
        try:
            return AsyncModbusSerialClient(
                port,
                framer=FramerType.RTU,
                baudrate=regs.BAUDRATE,
                bytesize=regs.BYTESIZE,
                parity=regs.PARITY,
                stopbits=regs.STOPBITS,
                timeout=timeout,
                retries=0,
                reconnect_delay=0,
            )
        except RuntimeError as exc:  # pymodbus without pyserial
            raise DeviceError(DEVICE, f"cannot open serial port {port}: {exc}") from exc

    return make_client


def tcp_client(host: str, port: int, timeout: float) -> Callable[[], ModbusClient]:
    """What builds the client of RTU frames over TCP (the simulator, a gateway)."""

    def make_client() -> ModbusClient:
        return AsyncModbusTcpClient(
            host, port=port, framer=FramerType.RTU, timeout=timeout, retries=0, reconnect_delay=0
        )

    return make_client


def cancel_requests() -> int:
    """How many cancellations the current task has been asked for and not yet absorbed."""
    task = asyncio.current_task()
    return task.cancelling() if task is not None else 0


def cancel_dropped(before: int) -> bool:
    """Did a cancellation come, and pymodbus swallow it, while we awaited it?

    pymodbus bounds its connect and each transaction with asyncio.wait_for, which
    on Python 3.11 returns the result and drops a cancellation that lands in the
    loop turns between the result and wait_for returning (CPython gh-86296). A
    run's valve or setpoint write cancelled by an e-stop would go on as if never
    cancelled: the run would start its next move after the stop, and the worker
    wait emergency_stop_timeout for it. The task still counts the request, so
    the caller raises it again (an `asyncio.timeout` expiring then still turns it
    into TimeoutError).
    """
    return cancel_requests() > before


class LineArbiter:
    """Mutual exclusion on the Modbus line with priorities (FIFO within a priority).

    An asyncio.Lock is FIFO only, so a valve close could queue behind polls and
    setpoint writes; here the lowest priority number goes first. A waiter taken
    as droppable (a valve opening) can be refused while it waits (`drop_waiting`).
    """

    def __init__(self, levels: int = 3) -> None:
        self._busy = False
        self._queues: list[deque[asyncio.Future[None]]] = [deque() for _ in range(levels)]
        self._droppable: set[asyncio.Future[None]] = set()

    @property
    def busy(self) -> bool:
        return self._busy

    async def acquire(self, priority: int, *, droppable: bool = False) -> None:
        if not self._busy and not any(self._queues):
            self._busy = True
            return
        waiter: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._queues[priority].append(waiter)
        if droppable:
            self._droppable.add(waiter)
        try:
            await waiter
        except asyncio.CancelledError:
            if waiter.done() and not waiter.cancelled():
                self.release()  # the line was handed to us just as we gave up: pass it on
            elif waiter in self._queues[priority]:  # release() may have passed it over
                self._queues[priority].remove(waiter)
            raise
        finally:
            self._droppable.discard(waiter)

    def release(self) -> None:
        for queue in self._queues:
            while queue:
                waiter = queue.popleft()
                if not waiter.done():
                    waiter.set_result(None)  # ownership passes on; _busy stays True
                    return
        self._busy = False

    def drop_waiting(self) -> int:
        """Refuse every droppable waiter still queued (each raises CancelledError); how many."""
        dropped = [waiter for waiter in self._droppable if not waiter.done()]
        for waiter in dropped:
            waiter.cancel()
        return len(dropped)
