"""A network simulator of the glue dispenser: Modbus RTU frames carried over TCP.

It serves the register map of `server.drivers.glue_registers` with a pymodbus
server using the RTU framer on a TCP socket, so the production client
(`ModbusGlueDispenser.tcp`, also RTU-framed) is exercised byte for byte as on
the RS-485 line, CRC included. Like a real RS-485 slave it stays silent for
requests addressed to another device id. Holding registers accept FC3/FC6/FC16
and input registers FC4 only; anything else gets exception 1 or 2, and an
out-of-range setpoint gets exception 3.

Model (computed from elapsed time whenever a register is read, no background
task): the valve feedback follows the command at once; measured flow
approaches the flow setpoint first-order (time constant 50 ms) while the valve
is open and is zero while it is closed; pressure approaches the pressure
setpoint (time constant 100 ms); temperature drifts slowly around 25 °C; flow,
pressure and temperature carry a little noise. With `speed_source` set (the
robot simulator (`ArmSpeed`), wired where both run in one process) it is a
speed-following dispenser, as real cells use: the active flow setpoint and the
flow out of the nozzle are the programmed ones scaled by the robot's actual speed
over its commanded one, so the glue per millimetre of bead does not depend on how
long the arm waits between moves (a run stretched by a busy machine does not
over-dispense) nor on how fast the simulated arm is made to move (a robot
simulator at speed_factor 4 draws a bead in a quarter of the time, and the flow is
four times the setpoint meanwhile); a valve opened with the arm at rest (a purge)
gives the fixed flow until the arm moves (a purge, all along; a run resumed after
a pause, until the arm sets off again, then the flow follows it). Flows are ml per
minute of wall time, and `dispensed_ml` is their integral on it: over the stretches the
arm moved (`RobotSimulator.motion_between`) and the flow model's exact mean between two
reads, so it does not depend on how often the dispenser is read. The totaliser registers
(DISPENSED_HIGH/LOW) count what the flow meter measures: `dispensed_ml`, or the pinned
flow while `force_flow` holds the reading. `speed_factor` > 1 makes the dynamics
faster (the flow's and the pressure's time constants, a late valve, the
temperature's drift), like the cell's `simulation_speed_factor`. `close_commanded_at`
is the time.time() of the last write of "closed" to the valve command; `valve_closed_at`
is the time.time() of the last open → closed transition, for latency benchmarks;
`valve_log` lists every change as (time.time(), open), so a test can tell
which stretch of the robot's executed path was sprayed.

Fault injection, in-process: `inject_no_reply(seconds=None)` (requests are
read and dropped, the connection stays open), `set_alarm(name)` /
`clear_alarm(name)`, `force_pressure(psi)` (measured pressure pinned),
`force_flow(ml_min)` (measured flow pinned while the valve is open: a blocked
or starved nozzle), `force_temperature(c)` (measured temperature pinned),
`inject_exception(code)` (every request answered with that Modbus exception),
`inject_stuck_valve()` (the valve ignores its command), `clog_nozzle(fraction)` (a
partly clogged nozzle: the flow out of it, and so its reading, drops to that fraction of the
setpoint), `delay_valve(ms)` (a valve that opens `ms` milliseconds of simulated time after its
open command; its feedback follows the valve), `clear_faults()`.
`history` lists every change of what leaves the nozzle as (time.time(), valve open, the flow
the nozzle tends to in ml/min), so the simulated camera can render the bead actually dispensed
(`glue_flow.flow_at` replays the flow model over it).
Out of process, the same through the control channel: JSON lines over TCP on
`control_port`, one request object per line and one reply line each, e.g.
  {"cmd": "no_reply", "seconds": 2.0}   seconds omitted or null: until cleared
  {"cmd": "alarm", "name": "HIGH_PRESSURE"}   {"cmd": "clear_alarm", "name": ...}
  {"cmd": "force_pressure", "psi": 180.0}     {"cmd": "exception", "code": 4}
  {"cmd": "force_flow", "ml_min": 5.0}        {"cmd": "force_temperature", "c": 70.0}
  {"cmd": "stuck_valve"}   {"cmd": "clog", "fraction": 0.4}   {"cmd": "late_valve", "ms": 150}
  {"cmd": "clear"}   {"cmd": "status"}
answered {"ok": true, ...} or {"ok": false, "error": "..."}. The control
channel always answers, even while Modbus replies are suppressed.

Run alone with:
  python -m server.drivers.sim.glue_sim --host 127.0.0.1 --port 5020 [--control-port N]
It prints `glue simulator control on HOST:PORT` (with --control-port) and then
`glue simulator listening on HOST:PORT` once both are accepting, and exits
cleanly on SIGTERM or SIGINT.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import contextlib
import json
import logging
import math
import random
import sys
import time
from typing import Any, Protocol

from pymodbus import FramerType
from pymodbus.constants import ExcCodes
from pymodbus.pdu import ModbusPDU
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from server.drivers import glue_registers as regs
from server.drivers.glue_registers import Register, Table
from server.drivers.sim.glue_flow import FLOW_TIME_CONSTANT_S
from server.drivers.sim.standalone import serve_until_signalled, stopped_by_signals

logger = logging.getLogger(__name__)


class ArmSpeed(Protocol):
    """What a speed-following dispenser follows: the robot simulator's speed."""

    def speed_fraction(self) -> float:
        """The arm's actual speed over its commanded one, now."""

    def motion_between(self, since: float, until: float) -> list[tuple[float, float, float]]:
        """(start, end, fraction) of each stretch of [since, until] the arm moved."""


PRESSURE_TIME_CONSTANT_S = 0.1
AMBIENT_C = 25.0
# A valve opened after the arm has stood still this long gives the fixed flow until the
# arm moves, as a speed-following controller does with no motion to follow (a purge, which
# lets the arm settle first: server/core/worker/purging.py); a run opens it on its way,
# or, resumed after a pause, just before the arm sets off again.
FIXED_FLOW_AFTER_S = 1.0
_HOLDING_FCS = {3, 6, 16}
_INPUT_FCS = {4}
_CONTROL_LINE_LIMIT = 64 * 1024
VALVE_LOG_SIZE = 10_000
HISTORY_SIZE = 20_000


class GlueSimulator:
    """A glue dispenser on a TCP port, speaking Modbus RTU frames."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        device_id: int = regs.DEFAULT_DEVICE_ID,
        control_port: int | None = None,
        speed_factor: float = 1.0,
        noise: bool = True,
        seed: int | None = None,
    ) -> None:
        if speed_factor <= 0:
            raise ValueError(f"speed_factor must be > 0, got {speed_factor}")
        self.host = host
        self._requested_port = port
        self._requested_control_port = control_port
        self.device_id = device_id
        self._speed = speed_factor
        self._noise = noise
        self._rng = random.Random(seed)
        self._server: ModbusTcpServer | None = None
        self._control: asyncio.Server | None = None
        self._control_writers: set[asyncio.StreamWriter] = set()
        self.port = 0
        self.control_port: int | None = None
        # model state
        self._valve_open = False
        self._flow_sp = 0.0
        self._pressure_sp = 0.0
        self._flow = 0.0
        self._pressure = 0.0
        self._started = time.monotonic()
        self._last_update = self._started
        self.valve_closed_at: float | None = None
        self.valve_opened_at: float | None = None
        # (time.time(), open) per valve change, the last VALVE_LOG_SIZE of them
        self.valve_log: collections.deque[tuple[float, bool]] = collections.deque(
            maxlen=VALVE_LOG_SIZE
        )
        self.close_commanded_at: float | None = None
        # (time.time(), valve open, flow the nozzle tends to) per change, for the bead's render
        self.history: collections.deque[tuple[float, bool, float]] = collections.deque(
            maxlen=HISTORY_SIZE
        )
        self._opens_at: tuple[float, float] | None = None  # (monotonic, time.time()) of a late open
        # faults
        self._clog = 1.0
        self._valve_delay_s = 0.0
        self._alarm_bits = 0
        self._forced_pressure: float | None = None
        self._forced_flow: float | None = None
        self._forced_temperature: float | None = None
        self._no_reply = False
        self._no_reply_until: float | None = None
        self._exception_code: int | None = None
        self._valve_stuck = False
        self.dropped_requests = 0
        # The robot's speed as a fraction of its programmed one (None: a fixed flow).
        self.speed_source: ArmSpeed | None = None
        self._fixed_flow = False  # the valve opened with the arm at rest: no speed to follow
        self.dispensed_ml = 0.0  # glue out of the nozzle so far (the flow model's integral)
        self._metered_ml = 0.0  # what the flow meter counted: the totaliser registers

    # --- lifecycle ---------------------------------------------------------------

    async def start(self) -> None:
        """Start serving Modbus (and the control channel, if a control port was given)."""
        if self._server is not None:
            return
        self._started = self._last_update = time.monotonic()
        device = SimDevice(
            id=self.device_id,
            simdata=[
                SimData(
                    address=r.address,
                    values=0,
                    datatype=DataType.REGISTERS,
                    readonly=not r.writable,
                )
                for r in regs.REGISTERS
            ],
            action=self._on_access,
        )
        server = ModbusTcpServer(
            device,
            framer=FramerType.RTU,
            address=(self.host, self._requested_port),
            # pymodbus drops a request its trace_pdu returns None for; its hint says ModbusPDU.
            trace_pdu=self._filter_request,  # type: ignore[arg-type]
        )
        await server.serve_forever(background=True)  # RuntimeError if the port is taken
        self._server = server
        self.port = server.transport.sockets[0].getsockname()[1]  # type: ignore[attr-defined]
        if self._requested_control_port is not None:
            try:
                self._control = await asyncio.start_server(
                    self._serve_control,
                    self.host,
                    self._requested_control_port,
                    limit=_CONTROL_LINE_LIMIT,
                )
            except OSError:
                await self.stop()
                raise
            self.control_port = self._control.sockets[0].getsockname()[1]
        logger.info("glue simulator listening on %s:%d", self.host, self.port)

    async def stop(self) -> None:
        """Stop serving and drop every connection; safe to call twice."""
        if self._control is not None:
            self._control.close()
            self._control = None
        for writer in list(self._control_writers):
            writer.close()
        if self._server is not None:
            server, self._server = self._server, None
            with contextlib.suppress(Exception):
                await server.shutdown()

    async def __aenter__(self) -> GlueSimulator:
        await self.start()
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.stop()

    # --- what a test may look at ------------------------------------------------

    @property
    def speed_factor(self) -> float:
        """How much faster than real time the dispenser's dynamics run."""
        return self._speed

    @property
    def valve_open(self) -> bool:
        """The valve position now (the VALVE_STATE feedback)."""
        self._settle_valve()
        return self._valve_open

    async def read_register(self, register: Register) -> int:
        """A register's raw value exactly as a Modbus client would read it now."""
        if self._server is None:
            raise RuntimeError("the glue simulator is not running")
        values = await self._server.async_getValues(
            self.device_id, register.table.read_function_code, register.address, 1
        )
        return int(values[0])

    def status(self) -> dict[str, Any]:
        """A snapshot of the model and the active faults (also the control channel's `status`)."""
        self._advance()
        return {
            "valve_open": self._valve_open,
            "flow_setpoint_ml_min": self._flow_sp,
            "pressure_setpoint_psi": self._pressure_sp,
            "flow_ml_min": round(self._flow, 3),
            "pressure_psi": round(self._measured_pressure(), 3),
            "alarms": list(regs.alarm_names(self._alarm_bits)),
            "no_reply": self._replies_suppressed(),
            "exception_code": self._exception_code,
            "valve_stuck": self._valve_stuck,
            "clog_fraction": self._clog,
            "valve_delay_ms": self._valve_delay_s * 1000.0,
            "forced_pressure_psi": self._forced_pressure,
            "forced_flow_ml_min": self._forced_flow,
            "forced_temperature_c": self._forced_temperature,
            "dispensed_ml": round(self._metered_ml, 6),
            "valve_closed_at": self.valve_closed_at,
            "dropped_requests": self.dropped_requests,
        }

    # --- fault injection ---------------------------------------------------------

    def inject_no_reply(self, seconds: float | None = None) -> None:
        """Stop answering Modbus requests (connections stay open) for `seconds` or until cleared."""
        self._no_reply = True
        self._no_reply_until = None if seconds is None else time.monotonic() + seconds

    def set_alarm(self, name: str) -> None:
        """Raise an alarm bit by name, e.g. "HIGH_PRESSURE"."""
        self._alarm_bits |= regs.alarm_bits([name])

    def clear_alarm(self, name: str) -> None:
        """Drop one alarm bit by name."""
        self._alarm_bits &= ~regs.alarm_bits([name])

    def force_pressure(self, psi: float | None) -> None:
        """Pin the measured pressure to `psi` (None releases it)."""
        if psi is not None:
            regs.PRESSURE_MEASURED.encode(psi)  # refuse what the register cannot carry
        self._forced_pressure = psi

    def force_flow(self, ml_min: float | None) -> None:
        """Pin the measured flow to `ml_min` while the valve is open (None releases it)."""
        if ml_min is not None:
            regs.FLOW_MEASURED.encode(ml_min)
        self._forced_flow = ml_min

    def force_temperature(self, celsius: float | None) -> None:
        """Pin the measured temperature to `celsius` (None releases it)."""
        if celsius is not None:
            regs.TEMPERATURE.encode(celsius)
        self._forced_temperature = celsius

    def inject_exception(self, code: int = ExcCodes.DEVICE_FAILURE) -> None:
        """Answer every Modbus request with exception `code` until cleared."""
        if code not in regs.MODBUS_EXCEPTIONS:
            raise ValueError(f"unknown Modbus exception code {code}")
        self._exception_code = int(code)

    def inject_stuck_valve(self) -> None:
        """The valve stays where it is whatever it is commanded (VALVE_STATE keeps reporting it)."""
        self._valve_stuck = True

    def clog_nozzle(self, fraction: float) -> None:
        """A partly clogged nozzle: the flow drops to `fraction` (0..1) of its setpoint.

        Unlike `force_flow`, the glue really stops coming: the bead the camera shows thins
        with it, and the flow reading shows the drop (1.0 clears it).
        """
        if not 0.0 <= fraction <= 1.0:
            raise ValueError(f"clog fraction is between 0 and 1, got {fraction}")
        self._advance()
        self._clog = float(fraction)
        self._note_history()

    def delay_valve(self, ms: float) -> None:
        """The valve opens `ms` milliseconds (simulated time) after each open command (0 clears)."""
        if not 0.0 <= ms <= 60_000.0:
            raise ValueError(f"valve delay is between 0 and 60000 ms, got {ms}")
        self._valve_delay_s = float(ms) / 1000.0

    def clear_faults(self) -> None:
        """Remove every injected fault: replies, alarms, pressure, exceptions, stuck valve,
        clog and late valve."""
        if self._clog != 1.0:
            self.clog_nozzle(1.0)
        self._valve_delay_s = 0.0
        self._valve_stuck = False
        self._no_reply = False
        self._no_reply_until = None
        self._alarm_bits = 0
        self._forced_pressure = None
        self._forced_flow = None
        self._forced_temperature = None
        self._exception_code = None

    # --- the dispenser model -----------------------------------------------------

    def _note_history(self, at: float | None = None) -> None:
        """Record what leaves the nozzle from now (or `at`) on."""
        target = self._flow_sp * self._clog
        self.history.append((time.time() if at is None else at, self._valve_open, target))

    def _settle_valve(self) -> None:
        """A late open whose time has come happens now (stamped when it was due)."""
        due = self._opens_at
        if due is not None and time.monotonic() >= due[0]:
            self._opens_at = None
            self._open_valve(due[1])

    def _open_valve(self, wall: float) -> None:
        now = time.monotonic()
        arm = self.speed_source
        self._fixed_flow = arm is None or not arm.motion_between(now - FIXED_FLOW_AFTER_S, now)
        self.valve_opened_at = wall
        self.valve_log.append((wall, True))
        self._valve_open = True
        self._note_history(wall)

    def _advance(self) -> None:
        """Move the first-order flow and pressure models to now."""
        self._settle_valve()
        now = time.monotonic()
        wall = now - self._last_update
        dt = wall * self._speed
        followed = self._followed(self._last_update, now)
        self._last_update = now
        if self._valve_open:
            target = self._flow_sp * self._clog
            steps = dt / FLOW_TIME_CONSTANT_S
            gain = 1 - math.exp(-steps)
            # The first-order flow's mean over the interval, in ml per minute of wall time.
            mean = target + (self._flow - target) * (gain / steps if steps > 0 else 1.0)
            self.dispensed_ml += mean * followed / 60.0
            forced = self._forced_flow
            self._metered_ml += (mean * followed if forced is None else forced * wall) / 60.0
            self._flow += (target - self._flow) * gain
        else:
            self._flow = 0.0
        gain = 1 - math.exp(-dt / PRESSURE_TIME_CONSTANT_S)
        self._pressure += (self._pressure_sp - self._pressure) * gain

    def _jitter(self, sigma: float) -> float:
        return self._rng.gauss(0.0, sigma) if self._noise else 0.0

    def _measured_pressure(self) -> float:
        if self._forced_pressure is not None:
            return self._forced_pressure
        return max(0.0, self._pressure + self._jitter(0.05))

    def _follow(self) -> float:
        """The speed-following factor now (module docstring): the robot's speed fraction,
        or 1.0, the fixed flow, for a valve opened with the arm at rest (a purge) until the
        arm moves: once there is motion to follow, the flow follows it to the close."""
        if self.speed_source is None or self._fixed_flow:
            return 1.0
        return self.speed_source.speed_fraction()

    def _followed(self, since: float, until: float) -> float:
        """The seconds of [since, until] weighted by the speed-following factor: the wall
        time at a fixed flow, the arm's motion once there is motion to follow."""
        if self.speed_source is None:
            return until - since
        spans = self.speed_source.motion_between(since, until)
        moved = sum((end - start) * fraction for start, end, fraction in spans)
        if not self._fixed_flow:
            return moved
        if not spans:
            return until - since
        self._fixed_flow = False
        return spans[0][0] - since + moved

    def _refresh(self, registers: list[int]) -> None:
        """Write the model's present values into the input registers."""
        self._advance()
        elapsed = (time.monotonic() - self._started) * self._speed
        follow = self._follow()
        flow = max(0.0, (self._flow + self._jitter(0.1)) * follow) if self._valve_open else 0.0
        if self._forced_flow is not None and self._valve_open:
            flow = self._forced_flow
        temperature = AMBIENT_C + 1.5 * math.sin(2 * math.pi * elapsed / 600.0) + self._jitter(0.02)
        if self._forced_temperature is not None:
            temperature = self._forced_temperature
        values = {
            regs.VALVE_STATE: int(self._valve_open),
            regs.FLOW_SETPOINT_ACTIVE: regs.FLOW_SETPOINT_ACTIVE.encode(self._flow_sp * follow),
            regs.PRESSURE_SETPOINT_ACTIVE: regs.PRESSURE_SETPOINT_ACTIVE.encode(self._pressure_sp),
            regs.FLOW_MEASURED: regs.FLOW_MEASURED.encode(flow, clamp=True),
            regs.PRESSURE_MEASURED: regs.PRESSURE_MEASURED.encode(
                self._measured_pressure(), clamp=True
            ),
            regs.TEMPERATURE: regs.TEMPERATURE.encode(temperature, clamp=True),
            regs.ALARM_BITS: self._alarm_bits,
            regs.UPTIME: int(elapsed) & 0xFFFF,
        }
        values[regs.DISPENSED_HIGH], values[regs.DISPENSED_LOW] = regs.encode_dispensed(
            self._metered_ml
        )
        for register, raw in values.items():
            registers[register.address] = raw

    def _apply_write(self, register: Register, raw: int) -> None:
        """Take a command or setpoint write (already checked against the register's range)."""
        value = register.decode(raw)
        self._advance()
        if register is regs.VALVE_COMMAND and not raw:
            self.close_commanded_at = time.time()  # every close command, even if already closed
        if register is regs.VALVE_COMMAND and not self._valve_stuck:
            now_open = bool(raw)
            if not now_open:
                self._opens_at = None  # a late open still pending never happens
            if self._valve_open and not now_open:
                self.valve_closed_at = time.time()
                self.valve_log.append((self.valve_closed_at, False))
                self._valve_open = False
                self._note_history(self.valve_closed_at)
            elif now_open and not self._valve_open and self._opens_at is None:
                if self._valve_delay_s > 0:
                    delay = self._valve_delay_s / self._speed
                    self._opens_at = (time.monotonic() + delay, time.time() + delay)
                else:
                    self._open_valve(time.time())
        elif register is regs.FLOW_SETPOINT:
            self._flow_sp = value
            self._note_history()
        elif register is regs.PRESSURE_SETPOINT:
            self._pressure_sp = value

    async def _on_access(
        self,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        """pymodbus calls this on every register access, before it reads or writes the block."""
        if self._exception_code is not None:
            return ExcCodes(self._exception_code)
        if function_code in _HOLDING_FCS:
            table = Table.HOLDING
        elif function_code in _INPUT_FCS:
            table = Table.INPUT
        else:
            return ExcCodes.ILLEGAL_FUNCTION
        targets = [regs.register_at(table, a) for a in range(address, address + count)]
        if any(t is None for t in targets):
            return ExcCodes.ILLEGAL_ADDRESS
        if set_values is not None:
            # validate the whole write first so a multi-register write is all or nothing
            for register, raw in zip(targets, set_values, strict=True):
                assert register is not None
                if not register.minimum <= register.decode(int(raw)) <= register.maximum:
                    return ExcCodes.ILLEGAL_VALUE
            for register, raw in zip(targets, set_values, strict=True):
                assert register is not None
                self._apply_write(register, int(raw))
            registers[regs.VALVE_STATE.address - start_address] = int(self._valve_open)
        elif table is Table.INPUT:
            self._refresh(registers)
        return None

    def _replies_suppressed(self) -> bool:
        until = self._no_reply_until
        if self._no_reply and until is not None and time.monotonic() >= until:
            self._no_reply = False
            self._no_reply_until = None
        return self._no_reply

    def _filter_request(self, sending: bool, pdu: ModbusPDU) -> ModbusPDU | None:
        """Drop requests for another device id or while no-reply is injected (no response sent)."""
        if sending:
            return pdu
        if pdu.dev_id != self.device_id or self._replies_suppressed():
            self.dropped_requests += 1
            return None
        return pdu

    # --- control channel ---------------------------------------------------------

    def control(self, request: dict[str, Any]) -> dict[str, Any]:
        """Carry out one control-channel request (also usable in-process)."""
        cmd = request.get("cmd")
        if cmd == "no_reply":
            seconds = request.get("seconds")
            self.inject_no_reply(None if seconds is None else float(seconds))
        elif cmd == "alarm":
            self.set_alarm(str(request.get("name")))
        elif cmd == "clear_alarm":
            self.clear_alarm(str(request.get("name")))
        elif cmd == "force_pressure":
            psi = request.get("psi")
            self.force_pressure(None if psi is None else float(psi))
        elif cmd == "force_flow":
            flow = request.get("ml_min")
            self.force_flow(None if flow is None else float(flow))
        elif cmd == "force_temperature":
            celsius = request.get("c")
            self.force_temperature(None if celsius is None else float(celsius))
        elif cmd == "exception":
            self.inject_exception(int(request.get("code", ExcCodes.DEVICE_FAILURE)))
        elif cmd == "stuck_valve":
            self.inject_stuck_valve()
        elif cmd == "clog":
            self.clog_nozzle(float(request.get("fraction", 0.5)))
        elif cmd == "late_valve":
            self.delay_valve(float(request.get("ms", 0.0)))
        elif cmd == "clear":
            self.clear_faults()
        elif cmd != "status":
            raise ValueError(
                f"unknown cmd {cmd!r}; use no_reply, alarm, clear_alarm, force_pressure, "
                "force_flow, force_temperature, exception, stuck_valve, clog, late_valve, clear "
                "or status"
            )
        return {"ok": True, "status": self.status()}

    async def _serve_control(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        self._control_writers.add(writer)
        try:
            while line := await reader.readline():
                if not line.strip():
                    continue
                try:
                    request = json.loads(line)
                    if not isinstance(request, dict):
                        raise ValueError("a control request is a JSON object")
                    reply = self.control(request)
                except (ValueError, TypeError) as exc:
                    reply = {"ok": False, "error": str(exc)}
                writer.write(json.dumps(reply).encode() + b"\n")
                await writer.drain()
        except asyncio.CancelledError:
            raise
        except (ConnectionError, asyncio.LimitOverrunError, asyncio.IncompleteReadError) as exc:
            logger.debug("glue simulator control connection ended: %s", exc)
        finally:
            self._control_writers.discard(writer)
            writer.close()


async def _run(args: argparse.Namespace) -> None:
    sim = GlueSimulator(
        args.host,
        args.port,
        device_id=args.device_id,
        control_port=args.control_port,
        speed_factor=args.speed_factor,
    )
    stop = stopped_by_signals()
    try:
        await sim.start()
    except (OSError, RuntimeError) as exc:
        print(f"glue simulator could not start on {args.host}:{args.port}: {exc}", file=sys.stderr)
        raise SystemExit(2) from exc
    if sim.control_port is not None:
        print(f"glue simulator control on {sim.host}:{sim.control_port}", flush=True)
    await serve_until_signalled(sim, "glue simulator", stop)


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point: serve until SIGTERM/SIGINT."""
    parser = argparse.ArgumentParser(description="Glue dispenser simulator (Modbus RTU over TCP)")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=5020, help="Modbus port (0: any free port)")
    parser.add_argument("--device-id", type=int, default=regs.DEFAULT_DEVICE_ID)
    parser.add_argument("--control-port", type=int, default=None, help="JSON-lines fault control")
    parser.add_argument("--speed-factor", type=float, default=1.0)
    parser.add_argument("--log-level", default="WARNING")
    args = parser.parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), stream=sys.stderr)
    asyncio.run(_run(args))
    return 0


if __name__ == "__main__":
    sys.exit(main())
