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
take turns on the line through `glue_line.LineArbiter`, which serves a valve close
before queued commands and queued commands before monitor polls. Each
exchange is one short request (a status poll is a single 8-register read), so
`set_valve(False)` waits at most for the one exchange already on the wire.
`set_valve(False)` then reads VALVE_STATE back (one more short read, retried
for `valve_settle_s` while the valve moves) and raises DeviceError if the valve
still reports open: closing is the safety-relevant direction and costs about
2 ms at 115200 baud. Opening is not read back; the monitor sees the feedback.

Cancellation: pymodbus bounds its connect and each transaction with
asyncio.wait_for, which on Python 3.11 drops a cancellation landing as the
reply arrives (CPython gh-86296); every exchange checks its task's pending
cancellations afterwards and raises the dropped one again (the line is then
clean, so the link is kept), so an e-stop's cancel of a run is never lost here.

Sessions: `new_session()` (a reset's probe calls it) begins a numbered
session. An exchange belongs to the session it was asked in; if it times out
or loses the link once a newer session has begun, the link is still dropped
(a late reply must not be misread) but no fault is reported and the health is
not marked down: a poll the dispenser swallowed before a reset must not send
the cell back to ERROR after the reset passed.

The monitor task (started by connect(), stopped by close()) polls the status
every `poll_interval` s, keeps `health.details` current (`status_at` is when
the reading was taken); `glue_status.StatusWatch` judges every reading and
reports once per onset, not on every poll: the dispenser's own alarms, pressure
(high at any time, low while spraying), flow off its setpoint while spraying,
and temperature.

Silence with the valve open cannot wait for `timeout` (15 s of unsupervised
glue). A watchdog task checks every `link_timeout / 5` s: while the valve may
be open (an open command was sent and no close has been read back since, or a
status read reported it open), an exchange that has waited longer than
`link_timeout` for its reply is a "VALVE_UNCONFIRMED" fault at once, saying
the valve could not be confirmed closed; the cell then stops the robot. The
watchdog also ends that exchange (as a timeout, dropping the link), so the
halt's valve close is sent at once rather than after `timeout`; while the
valve may be open, every later silent exchange is ended the same way. A
watchdog tick that itself came late (the event loop was held up) judges
nothing, so a busy process is never taken for a silent dispenser; the next
punctual tick decides.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable
from typing import Any, TypeVar

from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.pdu import ModbusPDU

from server.common.errors import DeviceDisconnected, DeviceError, DeviceTimeout
from server.drivers import glue_registers as regs
from server.drivers import wear
from server.drivers.base import DeviceFault, DeviceHealth, FaultListener, GlueStatus
from server.drivers.glue_line import (
    COMMAND,
    DEVICE,
    POLL,
    URGENT,
    LineArbiter,
    ModbusClient,
    cancel_dropped,
    cancel_requests,
    serial_client,
    tcp_client,
)
from server.drivers.glue_status import StatusWatch

logger = logging.getLogger(__name__)

WATCHDOG_TICKS = 5  # watchdog checks per link_timeout
_VALVE_READBACK_INTERVAL_S = 0.02

T = TypeVar("T")


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
        flow_tolerance_pct: float | None = None,
        flow_deviation_s: float = 0.5,
        temperature_range_c: tuple[float, float] | None = None,
        link_timeout: float | None = None,
        valve_settle_s: float = 0.2,
        link_hint: str = "",
    ) -> None:
        """Prefer `serial()` and `tcp()`; `make_client` builds the pymodbus client on connect().

        `flow_tolerance_pct`, `temperature_range_c` and `link_timeout` None switch
        that check off (the driver alone checks nothing the cell did not ask for;
        the cell's settings switch them on with real defaults).
        """
        if timeout <= 0:
            raise ValueError(f"timeout must be > 0 s, got {timeout}")
        if link_timeout is not None and link_timeout <= poll_interval:
            raise ValueError(
                f"link_timeout ({link_timeout:g} s) must be longer than poll_interval "
                f"({poll_interval:g} s), or every pause between polls would look like silence"
            )
        self._make_client = make_client
        self.where = where
        self.device_id = device_id
        self.timeout = timeout
        self.poll_interval = poll_interval
        self.pressure_range_psi = pressure_range_psi
        self.flow_tolerance_pct = flow_tolerance_pct
        self.flow_deviation_s = flow_deviation_s
        self.temperature_range_c = temperature_range_c
        self.link_timeout = link_timeout
        self.valve_settle_s = valve_settle_s
        self._link_hint = link_hint
        self.health = DeviceHealth(name=DEVICE, details={"link": where, "device_id": device_id})
        self._client: ModbusClient | None = None
        self._line = LineArbiter()
        self._listener: FaultListener | None = None
        self._monitor: asyncio.Task[None] | None = None
        self._running = False
        self._link_fault = False
        self._session = 0  # see "Sessions" in the module doc
        self._line_session = 0  # the session of the exchange on the line now
        self._watch = StatusWatch(
            self._report,
            pressure_range_psi=pressure_range_psi,
            flow_tolerance_pct=flow_tolerance_pct,
            flow_deviation_s=flow_deviation_s,
            temperature_range_c=temperature_range_c,
        )
        # Valve supervision: may it be open, and what waits for the dispenser's answer.
        self._valve_may_be_open = False
        self._opening = 0  # open commands on their way: a poll must not clear the flag
        self._waiting_since: dict[int, float] = {}  # exchange -> monotonic time it was sent
        self._exchange_ids = 0
        self._unconfirmed_reported = False
        self._watchdog: asyncio.Task[None] | None = None
        self._on_line: asyncio.Timeout | None = None  # the deadline of the exchange on the line
        self._cut_short = False
        self._cancelled_after_reply = False  # a swallowed cancel raised again after a clean reply

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
        options.setdefault("link_hint", "check that it exists, is free and readable by this user")
        make_client = serial_client(port, timeout)
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
        where = f"{host}:{port} (RTU over TCP)"
        options.setdefault("link_hint", "check that the simulator or gateway is running")
        return cls(
            tcp_client(host, port, timeout), where, device_id=device_id, timeout=timeout, **options
        )

    # --- GlueDispenser -----------------------------------------------------------

    async def connect(self) -> None:
        """Open the link, read the status once, then start the monitor."""
        if self._client is not None:
            return
        self._watch.reset()  # a new session: alarms and excursions still present are news again
        self._unconfirmed_reported = False
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
        if self.link_timeout is not None:
            self._watchdog = asyncio.create_task(
                self._watchdog_loop(self.link_timeout), name="glue-dispenser-watchdog"
            )
        logger.info("glue dispenser connected on %s (device id %d)", self.where, self.device_id)

    async def close(self) -> None:
        """Stop the monitor and close the link; never raises."""
        self._running = False
        tasks = {t for t in (self._monitor, self._watchdog) if t is not None}
        self._monitor = self._watchdog = None
        for task in tasks:
            task.cancel()
        if tasks:
            await asyncio.wait(tasks)
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

        if not open_:
            await self._call(what, URGENT, body)
            return
        # Counted open from before the command may reach the line: a reply lost on
        # the way leaves a valve that may well be open.
        self._valve_may_be_open = True
        self._watch.valve_opening()
        self._opening += 1
        try:
            await self._call(what, COMMAND, body, droppable=True)
            wear.add(self.health.details, wear.VALVE_CYCLES, 1)  # an opening answered
        finally:
            self._opening -= 1

    @property
    def line_busy(self) -> bool:
        """An exchange is on the line now: a valve close asked for now is written once
        its reply is in (Modbus RTU carries one exchange at a time)."""
        return self._line.busy

    def drop_waiting_openings(self) -> int:
        """Refuse every valve opening still waiting for the line; how many there were.

        Each one's `set_valve(True)` raises CancelledError. A close goes ahead of
        whatever waits for the line, so an opening asked for before a halt would
        otherwise go out after the halt's close and open the valve again. An
        opening already on the line is left to finish: the close follows it.
        """
        return self._line.drop_waiting()

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
        """Where NO_REPLY, COMM_LOST, ALARM, PRESSURE_OUT_OF_RANGE, FLOW_DEVIATION,
        TEMPERATURE_OUT_OF_RANGE, VALVE_UNCONFIRMED and VALVE_STUCK_OPEN go."""
        self._listener = listener

    def new_session(self) -> int:
        """Begin a new session: exchanges already asked for can no longer fault the dispenser."""
        self._session += 1
        return self._session

    # --- exchanges ---------------------------------------------------------------

    async def _call(
        self,
        what: str,
        priority: int,
        body: Callable[[], Awaitable[T]],
        *,
        droppable: bool = False,
    ) -> T:
        """Run `body` on the line within `timeout`, classifying a timeout by where it hit;
        `droppable`: `drop_waiting_openings` may refuse it while it waits for the line."""
        on_line = False
        session = self._session
        try:
            async with asyncio.timeout(self.timeout) as deadline:
                await self._line.acquire(priority, droppable=droppable)
                on_line = True
                self._line_session = session
                self._on_line = deadline  # the watchdog may cut a silent exchange short
                try:
                    return await body()
                finally:
                    self._on_line = None
                    self._line.release()
        except TimeoutError:
            self._cancelled_after_reply = False
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
            if self._cut_short:
                self._cut_short = False
                message = (
                    f"{what}: no reply within the link timeout ({self.link_timeout:g} s) "
                    f"while the valve may be open, from device {self.device_id} on {self.where}"
                )
            else:
                message = (
                    f"{what}: no reply within {self.timeout:g} s from device {self.device_id} "
                    f"on {self.where}; check power, wiring and the device id"
                )
            self._drop_link()
            self._link_lost("NO_REPLY", message)
            raise DeviceTimeout(DEVICE, message) from None
        except asyncio.CancelledError:
            answered, self._cancelled_after_reply = self._cancelled_after_reply, False
            if on_line and not answered:
                self._drop_link()  # a reply may still be on its way: start the next one clean
            raise

    async def _ensure_link(self) -> ModbusClient:
        client = self._client
        if client is None:
            raise DeviceDisconnected(DEVICE, f"not connected to {self.where}: call connect() first")
        if client.connected:
            return client
        before = cancel_requests()
        connected = await client.connect()
        if cancel_dropped(before):
            raise asyncio.CancelledError
        if not connected:
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
        self._exchange_ids += 1
        exchange = self._exchange_ids
        self._waiting_since[exchange] = time.monotonic()
        before = cancel_requests()
        try:
            response = await send(client)
            if cancel_dropped(before):
                self._cancelled_after_reply = True  # the line is clean: no need to drop it
                raise asyncio.CancelledError
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
        finally:
            self._waiting_since.pop(exchange, None)
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
                if not self._opening:
                    self._valve_may_be_open = False
                # What /health and the live feed show at once, before the next poll.
                wear.valve_open_held(self.health.details, now := time.time())
                self.health.details.update(valve_open=False, status_at=now)
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
        self._unconfirmed_reported = False
        self._cut_short = False
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
        """Update health.details and report the onsets one status read shows (module doc)."""
        details, now = self.health.details, time.time()
        wear.valve_open_held(details, now)
        wear.glue_counted(details, status.dispensed_ml)
        details.update(
            valve_open=status.valve_open,
            flow_ml_min=status.flow_ml_min,
            flow_setpoint_ml_min=status.flow_setpoint_ml_min,
            pressure_psi=status.pressure_psi,
            pressure_setpoint_psi=status.pressure_setpoint_psi,
            temperature_c=status.temperature_c,
            alarms=list(status.alarms),
            uptime_s=uptime_s,
            dispensed_ml=status.dispensed_ml,
            dispensed_at=now,  # a valve's read-back updates status_at, never the count
            status_at=now,
        )
        if status.valve_open:
            self._valve_may_be_open = True
        elif not self._opening:
            self._valve_may_be_open = False
        self.health.active_faults = self._watch.observe(status)

    async def _watchdog_loop(self, link_timeout: float) -> None:
        """Silence while the valve may be open is a fault at once (see the module doc)."""
        tick = link_timeout / WATCHDOG_TICKS
        last = time.monotonic()
        while True:
            await asyncio.sleep(tick)
            now = time.monotonic()
            punctual = now - last < 2 * tick
            last = now
            if not punctual or not self._valve_may_be_open:
                continue
            oldest = min(self._waiting_since.values(), default=now)
            silent_s = now - oldest
            if silent_s <= link_timeout:
                continue
            if not self._unconfirmed_reported:
                self._unconfirmed_reported = True
                self._link_fault = True  # this is the outage's report: no NO_REPLY after it
                message = (
                    f"the glue dispenser on {self.where} has not answered for {silent_s:.2f} s "
                    f"(link timeout {link_timeout:g} s) while the valve may be open: the valve "
                    "could not be confirmed closed; check the valve at the nozzle, then the "
                    "dispenser's power and wiring"
                )
                self.health.record_error(message, connected=False)
                logger.error("glue dispenser: %s", message)
                self._report("VALVE_UNCONFIRMED", message)
            # End the silent exchange now (the link is dropped, so no late reply is taken
            # for another's): the halt's valve close must reach the line at once, not after
            # `timeout`, in case the silence was one lost frame.
            deadline = self._on_line
            if deadline is not None and not self._cut_short:
                self._cut_short = True
                deadline.reschedule(asyncio.get_running_loop().time())

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
