"""The glue dispenser driver: Modbus RTU on RS-485, or RTU frames over TCP to the simulator.

One class, two transports: `ModbusGlueDispenser.serial(port)` for the cell
(115200 baud, 8N1) and `ModbusGlueDispenser.tcp(host, port)` for the network
simulator, which carries the very same RTU frames (CRC included) over a TCP
socket. Addresses and scaling come only from `glue_registers`.

Timing: every public call finishes within `timeout` (the cell's
glue_system_timeout), waiting for the line included. pymodbus gets the same
timeout with `retries=0`, so its own retry loop can never stretch a call, and
`asyncio.timeout` is the hard bound. A dispenser that does not answer gives
`DeviceTimeout`, marks `health.connected` False, drops the link (a late reply
must not be taken for the answer to the next request: RTU frames carry no
transaction id) and reports `DeviceFault("glue", "NO_REPLY", ...)` once per
outage; the next call reconnects by itself. A refused connection gives
`DeviceDisconnected` and "COMM_LOST". A Modbus exception response gives
`DeviceError` naming the register. Out-of-range setpoints raise ValueError
before anything is sent.

The pymodbus client is not safe for concurrent transactions, so exchanges
take turns on the line through `_LineArbiter`, which serves a valve close
before queued commands and queued commands before monitor polls. Each
exchange is one short request (a status poll is a single 8-register read), so
`set_valve(False)` waits at most for the one exchange already on the wire.
`set_valve(False)` then reads VALVE_STATE back (one more short read, retried
for `valve_settle_s` while the valve moves) and raises DeviceError if the valve
still reports open: closing is the safety-relevant direction and costs about
2 ms at 115200 baud. Opening is not read back; the monitor sees the feedback.

Sessions: `new_session()` (a reset's probe calls it) begins a numbered
session. An exchange belongs to the session it was asked in; if it times out
or loses the link once a newer session has begun, the link is still dropped
(a late reply must not be misread) but no fault is reported and the health is
not marked down: a poll the dispenser swallowed before a reset must not send
the cell back to ERROR after the reset passed.

The monitor task (started by connect(), stopped by close()) polls the status
every `poll_interval` s, keeps `health.details` current and reports each new
alarm bit ("ALARM") and a measured pressure outside `pressure_range_psi`
("PRESSURE_OUT_OF_RANGE") once per onset, not on every poll.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from collections.abc import Awaitable, Callable
from typing import Any, TypeVar

from pymodbus import FramerType
from pymodbus.client import AsyncModbusSerialClient, AsyncModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.pdu import ModbusPDU

from server.drivers import glue_registers as regs
from server.drivers.base import DeviceFault, DeviceHealth, FaultListener, GlueStatus
from server.errors import DeviceDisconnected, DeviceError, DeviceTimeout

logger = logging.getLogger(__name__)

DEVICE = "glue"
URGENT, COMMAND, POLL = 0, 1, 2  # line priorities: valve close, commands, monitor polls
PRESSURE_HYSTERESIS_PSI = 1.0
_VALVE_READBACK_INTERVAL_S = 0.02

ModbusClient = AsyncModbusTcpClient | AsyncModbusSerialClient
T = TypeVar("T")


class _LineArbiter:
    """Mutual exclusion on the Modbus line with priorities (FIFO within a priority).

    An asyncio.Lock is FIFO only, so a valve close could queue behind polls and
    setpoint writes; here the lowest priority number goes first.
    """

    def __init__(self, levels: int = 3) -> None:
        self._busy = False
        self._queues: list[deque[asyncio.Future[None]]] = [deque() for _ in range(levels)]

    async def acquire(self, priority: int) -> None:
        if not self._busy and not any(self._queues):
            self._busy = True
            return
        waiter: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._queues[priority].append(waiter)
        try:
            await waiter
        except asyncio.CancelledError:
            if waiter.done() and not waiter.cancelled():
                self.release()  # the line was handed to us just as we gave up: pass it on
            else:
                self._queues[priority].remove(waiter)
            raise

    def release(self) -> None:
        for queue in self._queues:
            while queue:
                waiter = queue.popleft()
                if not waiter.done():
                    waiter.set_result(None)  # ownership passes on; _busy stays True
                    return
        self._busy = False


class ModbusGlueDispenser:
    """A `GlueDispenser` speaking Modbus RTU (see the module docstring for the timing rules)."""

    def __init__(
        self,
        make_client: Callable[[], ModbusClient],
        where: str,
        *,
        device_id: int = regs.DEFAULT_DEVICE_ID,
        timeout: float = 15.0,
        poll_interval: float = 0.2,
        pressure_range_psi: tuple[float, float] = (0.0, regs.PRESSURE_SETPOINT.maximum),
        valve_settle_s: float = 0.2,
        link_hint: str = "",
    ) -> None:
        """Prefer `serial()` and `tcp()`; `make_client` builds the pymodbus client on connect()."""
        if timeout <= 0:
            raise ValueError(f"timeout must be > 0 s, got {timeout}")
        self._make_client = make_client
        self.where = where
        self.device_id = device_id
        self.timeout = timeout
        self.poll_interval = poll_interval
        self.pressure_range_psi = pressure_range_psi
        self.valve_settle_s = valve_settle_s
        self._link_hint = link_hint
        self.health = DeviceHealth(name=DEVICE, details={"link": where, "device_id": device_id})
        self._client: ModbusClient | None = None
        self._line = _LineArbiter()
        self._listener: FaultListener | None = None
        self._monitor: asyncio.Task[None] | None = None
        self._running = False
        self._link_fault = False
        self._session = 0  # see "Sessions" in the module doc
        self._line_session = 0  # the session of the exchange on the line now
        self._active_alarms: frozenset[str] = frozenset()
        self._pressure_fault = False

    @classmethod
    def serial(
        cls,
        port: str,
        *,
        device_id: int = regs.DEFAULT_DEVICE_ID,
        timeout: float = 15.0,
        **options: Any,
    ) -> ModbusGlueDispenser:
        """The real dispenser on an RS-485 adapter (115200 baud, 8N1, Modbus RTU)."""

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

        options.setdefault("link_hint", "check that it exists, is free and readable by this user")
        where = f"serial port {port}"
        return cls(make_client, where, device_id=device_id, timeout=timeout, **options)

    @classmethod
    def tcp(
        cls,
        host: str,
        port: int,
        *,
        device_id: int = regs.DEFAULT_DEVICE_ID,
        timeout: float = 15.0,
        **options: Any,
    ) -> ModbusGlueDispenser:
        """The simulator (or a serial-to-TCP gateway in transparent mode): RTU frames over TCP."""

        def make_client() -> ModbusClient:
            return AsyncModbusTcpClient(
                host,
                port=port,
                framer=FramerType.RTU,
                timeout=timeout,
                retries=0,
                reconnect_delay=0,
            )

        where = f"{host}:{port} (RTU over TCP)"
        options.setdefault("link_hint", "check that the simulator or gateway is running")
        return cls(make_client, where, device_id=device_id, timeout=timeout, **options)

    # --- GlueDispenser -----------------------------------------------------------

    async def connect(self) -> None:
        """Open the link, read the status once, then start the monitor."""
        if self._client is not None:
            return
        # a new session: alarms and excursions still present are news again
        self._active_alarms = frozenset()
        self._pressure_fault = False
        try:
            self._client = self._make_client()
        except DeviceError as exc:
            self.health.record_error(str(exc), connected=False)
            raise
        try:
            await self._read_status(COMMAND)
        except BaseException:
            client, self._client = self._client, None
            if client is not None:
                client.close()
            self.health.connected = False
            raise
        self._running = True
        self._monitor = asyncio.create_task(self._monitor_loop(), name="glue-dispenser-monitor")
        logger.info("glue dispenser connected on %s (device id %d)", self.where, self.device_id)

    async def close(self) -> None:
        """Stop the monitor and close the link; never raises."""
        self._running = False
        task, self._monitor = self._monitor, None
        if task is not None:
            task.cancel()
            await asyncio.wait({task})
        client, self._client = self._client, None
        if client is not None:
            try:
                client.close()
            except Exception:
                logger.exception("closing the glue dispenser link failed")
        self.health.connected = False

    async def set_valve(self, open_: bool) -> None:
        """Open or close the valve; a close jumps the queue and is read back (see module doc)."""
        raw = regs.encode_valve(open_)
        what = f"{'open' if open_ else 'close'} valve via {regs.VALVE_COMMAND.label}"

        async def body() -> None:
            await self._write(regs.VALVE_COMMAND, raw, what)
            if not open_:
                await self._verify_closed(what)

        await self._call(what, COMMAND if open_ else URGENT, body)

    async def set_flow_rate(self, ml_per_min: float) -> None:
        """Set the flow setpoint (ml/min); ValueError outside the register's range."""
        raw = regs.encode_flow(ml_per_min)
        what = f"set {regs.FLOW_SETPOINT.label} to {ml_per_min:g} ml/min"
        await self._call(what, COMMAND, lambda: self._write(regs.FLOW_SETPOINT, raw, what))

    async def set_pressure(self, psi: float) -> None:
        """Set the pressure setpoint (PSI); ValueError outside the register's range."""
        raw = regs.encode_pressure(psi)
        what = f"set {regs.PRESSURE_SETPOINT.label} to {psi:g} PSI"
        await self._call(what, COMMAND, lambda: self._write(regs.PRESSURE_SETPOINT, raw, what))

    async def read_status(self) -> GlueStatus:
        """Valve, active setpoints, measurements and alarms, in one FC4 read."""
        return await self._read_status(COMMAND)

    def set_fault_listener(self, listener: FaultListener | None) -> None:
        """Where NO_REPLY, COMM_LOST, ALARM, PRESSURE_OUT_OF_RANGE and VALVE_STUCK_OPEN go."""
        self._listener = listener

    def new_session(self) -> int:
        """Begin a new session: exchanges already asked for can no longer fault the dispenser."""
        self._session += 1
        return self._session

    # --- exchanges ---------------------------------------------------------------

    async def _call(self, what: str, priority: int, body: Callable[[], Awaitable[T]]) -> T:
        """Run `body` on the line within `timeout`, classifying a timeout by where it hit."""
        on_line = False
        session = self._session
        try:
            async with asyncio.timeout(self.timeout):
                await self._line.acquire(priority)
                on_line = True
                self._line_session = session
                try:
                    return await body()
                finally:
                    self._line.release()
        except TimeoutError:
            if session != self._session:
                if on_line:
                    self._drop_link()  # a late reply must not be read as the next one's
                message = f"{what}: no reply within {self.timeout:g} s (asked before a reset)"
                logger.info("glue dispenser: %s; not a fault now", message)
                raise DeviceTimeout(DEVICE, message) from None
            if not on_line:
                message = (
                    f"{what}: the Modbus line stayed busy for {self.timeout:g} s "
                    "(an earlier exchange got no reply)"
                )
                self.health.record_error(message)
                raise DeviceTimeout(DEVICE, message) from None
            message = (
                f"{what}: no reply within {self.timeout:g} s from device {self.device_id} "
                f"on {self.where}; check power, wiring and the device id"
            )
            self._drop_link()
            self._link_lost("NO_REPLY", message)
            raise DeviceTimeout(DEVICE, message) from None
        except asyncio.CancelledError:
            if on_line:
                self._drop_link()  # a reply may still be on its way: start the next one clean
            raise

    async def _ensure_link(self) -> ModbusClient:
        client = self._client
        if client is None:
            raise DeviceDisconnected(DEVICE, f"not connected to {self.where}: call connect() first")
        if not client.connected and not await client.connect():
            message = f"cannot open the link to the glue dispenser on {self.where}"
            if self._link_hint:
                message += f"; {self._link_hint}"
            self._link_lost("COMM_LOST", message)
            raise DeviceDisconnected(DEVICE, message)
        return client

    async def _request(
        self, what: str, send: Callable[[ModbusClient], Awaitable[ModbusPDU]]
    ) -> ModbusPDU:
        """One Modbus transaction, with pymodbus errors turned into the cell's errors."""
        client = await self._ensure_link()
        started = time.perf_counter()
        try:
            response = await send(client)
        except ConnectionException as exc:
            message = f"{what}: link to {self.where} lost ({exc})"
            self._drop_link()
            self._link_lost("COMM_LOST", message)
            raise DeviceDisconnected(DEVICE, message) from exc
        except ModbusIOException as exc:
            if "No response" in str(exc):
                raise TimeoutError from exc  # same outcome as our own deadline
            self._drop_link()
            message = f"{what}: garbled reply from {self.where} ({exc})"
            self.health.record_error(message)
            raise DeviceError(DEVICE, message) from exc
        except ModbusException as exc:
            message = f"{what}: {exc}"
            self.health.record_error(message)
            raise DeviceError(DEVICE, message) from exc
        self._link_ok(time.perf_counter() - started)
        if response.isError():
            code = int(getattr(response, "exception_code", 0))
            message = f"{what} refused by the dispenser: {regs.exception_text(code)}"
            self.health.record_error(message)
            raise DeviceError(DEVICE, message)
        return response

    async def _write(self, register: regs.Register, raw: int, what: str) -> None:
        response = await self._request(
            what, lambda c: c.write_register(register.address, raw, device_id=self.device_id)
        )
        if list(response.registers) != [raw]:
            message = f"{what}: the dispenser echoed {response.registers}, not [{raw}]"
            self.health.record_error(message)
            raise DeviceError(DEVICE, message)

    async def _read_input(self, address: int, count: int, what: str) -> list[int]:
        response = await self._request(
            what, lambda c: c.read_input_registers(address, count=count, device_id=self.device_id)
        )
        if len(response.registers) != count:
            message = f"{what}: expected {count} registers, got {len(response.registers)}"
            self.health.record_error(message)
            raise DeviceError(DEVICE, message)
        return list(response.registers)

    async def _verify_closed(self, what: str) -> None:
        """Read VALVE_STATE until it reports closed or `valve_settle_s` has passed."""
        check = f"{what}: read back {regs.VALVE_STATE.label}"
        deadline = time.monotonic() + self.valve_settle_s
        while True:
            (state,) = await self._read_input(regs.VALVE_STATE.address, 1, check)
            if state == 0:
                return
            if time.monotonic() >= deadline:
                break
            await asyncio.sleep(_VALVE_READBACK_INTERVAL_S)
        message = (
            f"valve commanded closed but {regs.VALVE_STATE.label} still reports open after "
            f"{self.valve_settle_s:g} s; check the valve and its air supply"
        )
        self.health.record_error(message)
        self._report("VALVE_STUCK_OPEN", message)
        raise DeviceError(DEVICE, message)

    async def _read_status(self, priority: int) -> GlueStatus:
        first, count = regs.STATUS_ADDRESS, regs.STATUS_COUNT
        what = f"read status (input registers {first}-{first + count - 1})"
        raw = await self._call(what, priority, lambda: self._read_input(first, count, what))
        status = regs.decode_status(raw)
        self._observe(status, regs.decode_uptime(raw))
        return status

    # --- health and faults -------------------------------------------------------

    def _drop_link(self) -> None:
        """Close the transport so the next exchange reconnects and no stale reply is read."""
        if self._client is not None:
            try:
                self._client.close()
            except Exception:
                logger.exception("closing the glue dispenser link failed")

    def _link_ok(self, rtt_s: float) -> None:
        self.health.record_ok(rtt_s)
        if self._link_fault:
            self._link_fault = False
            logger.info("glue dispenser on %s answers again", self.where)

    def _link_lost(self, code: str, message: str) -> None:
        """Mark the link down; report once per outage, and only once connect() has succeeded."""
        if self._line_session != self._session:
            logger.info("glue dispenser: %s (asked before a reset; not a fault now)", message)
            return
        self.health.record_error(message, connected=False)
        if self._link_fault:
            return
        self._link_fault = True
        logger.warning("glue dispenser: %s", message)
        if self._running:
            self._report(code, message)

    def _report(self, code: str, message: str) -> None:
        listener = self._listener
        if listener is None:
            return
        try:
            listener(DeviceFault(DEVICE, code, message))
        except Exception:
            logger.exception("the glue fault listener failed on %s", code)

    def _observe(self, status: GlueStatus, uptime_s: int) -> None:
        """Update health.details and report alarm and pressure onsets from one status read."""
        self.health.details.update(
            valve_open=status.valve_open,
            flow_ml_min=status.flow_ml_min,
            flow_setpoint_ml_min=status.flow_setpoint_ml_min,
            pressure_psi=status.pressure_psi,
            pressure_setpoint_psi=status.pressure_setpoint_psi,
            temperature_c=status.temperature_c,
            alarms=list(status.alarms),
            uptime_s=uptime_s,
        )
        new = [name for name in status.alarms if name not in self._active_alarms]
        self._active_alarms = frozenset(status.alarms)
        if new:
            self._report(
                "ALARM",
                f"glue dispenser alarm: {', '.join(new)} (pressure {status.pressure_psi:g} PSI, "
                f"flow {status.flow_ml_min:g} ml/min, {status.temperature_c:g} °C)",
            )
        low, high = self.pressure_range_psi
        pressure = status.pressure_psi
        if not low <= pressure <= high:
            if not self._pressure_fault:
                self._pressure_fault = True
                self._report(
                    "PRESSURE_OUT_OF_RANGE",
                    f"glue pressure {pressure:g} PSI is outside the allowed {low:g}-{high:g} PSI "
                    f"(setpoint {status.pressure_setpoint_psi:g} PSI)",
                )
        elif self._pressure_fault:
            margin_low = low + PRESSURE_HYSTERESIS_PSI if low > 0 else low
            if margin_low <= pressure <= high - PRESSURE_HYSTERESIS_PSI:
                self._pressure_fault = False  # back inside with margin: the next excursion reports
        faults = [f"glue: alarm {', '.join(status.alarms)}"] if status.alarms else []
        if not low <= pressure <= high:
            faults.append(f"glue: pressure {pressure:.1f} PSI outside {low:g}..{high:g} PSI")
        self.health.active_faults = tuple(faults)

    async def _monitor_loop(self) -> None:
        """Poll the status in the background so alarms and silence surface without a command."""
        while True:
            await asyncio.sleep(self.poll_interval)
            try:
                await self._read_status(POLL)
            except asyncio.CancelledError:
                raise
            except DeviceError:
                pass  # already in health and, for a lost link, reported once
            except Exception:
                logger.exception("glue dispenser monitor poll failed")
