"""The glue dispenser's Modbus register map: pure data and pure functions, no I/O.

This is the one place that knows addresses, scalings and bit meanings, so the
driver (`glue_modbus`), the simulator (`sim.glue_sim`) and the document
(`docs/glue-register-map.md`, checked against this module by a unit test)
cannot disagree.

Layout choice: commands and setpoints are holding registers (read FC3, write
FC6/FC16) at 0-2; everything the dispenser measures or reports is an input
register (read-only, FC4) at 100-109. The input block also echoes the active
setpoints, so one FC4 read of 10 registers returns a whole `GlueStatus`: the
monitor poll is a single short exchange, which keeps the RS-485 line free for
a valve-close command. Addresses are unique across both tables so a register
is named unambiguously by its address alone in logs.

The dispenser's own totaliser (108-109, the glue it has dispensed since power-up,
counted in microlitres over 32 bits, high word first as Modbus devices put it)
is what a part's glue is measured by: a count kept on the device does not depend
on when the server's polls come, while flow readings integrated on the server
miss or stretch whatever happens between two polls on a busy machine.

All registers are 16 bits. Engineering value = raw × scale; temperature is a
signed (two's complement) register, every other one unsigned.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from enum import Enum, IntFlag

from server.drivers.base import GlueStatus

# --- serial line (RS-485, Modbus RTU) ------------------------------------------

BAUDRATE = 115200
BYTESIZE = 8
PARITY = "N"
STOPBITS = 1
DEFAULT_DEVICE_ID = 1


class Table(Enum):
    """The Modbus table a register lives in, with the function codes that reach it."""

    HOLDING = "holding"
    INPUT = "input"

    @property
    def read_function_code(self) -> int:
        """FC3 for holding registers, FC4 for input registers."""
        return 3 if self is Table.HOLDING else 4


@dataclass(frozen=True)
class Register:
    """One 16-bit register: where it is, what it means and how to scale it."""

    name: str
    address: int
    table: Table
    description: str
    unit: str = ""
    scale: float = 1.0
    minimum: float = 0.0
    maximum: float = 65535.0
    signed: bool = False

    @property
    def writable(self) -> bool:
        """True for command and setpoint registers."""
        return self.table is Table.HOLDING

    @property
    def label(self) -> str:
        """How error messages name the register, e.g. `FLOW_SETPOINT (holding register 1)`."""
        return f"{self.name} ({self.table.value} register {self.address})"

    def encode(self, value: float, *, clamp: bool = False) -> int:
        """Engineering value → raw register value.

        Out-of-range values raise ValueError naming the register and its limits,
        because a silently clipped setpoint is a wrong bead nobody notices.
        `clamp=True` is for the simulator's measurements, which saturate like a
        real sensor instead.
        """
        if isinstance(value, bool):
            value = int(value)
        if not isinstance(value, int | float) or not math.isfinite(value):
            raise ValueError(f"{self.name} needs a finite number, got {value!r}")
        if clamp:
            value = min(max(value, self.minimum), self.maximum)
        elif not self.minimum <= value <= self.maximum:
            unit = f" {self.unit}" if self.unit else ""
            raise ValueError(
                f"{self.name} must be between {self.minimum:g} and {self.maximum:g}{unit}, "
                f"got {value:g}"
            )
        raw = round(value / self.scale)
        return raw & 0xFFFF if self.signed else raw

    def decode(self, raw: int) -> float:
        """Raw register value → engineering value (no range check: report what the device says)."""
        if not 0 <= raw <= 0xFFFF:
            raise ValueError(f"{self.name}: a 16-bit register holds 0..65535, got {raw}")
        if self.signed and raw >= 0x8000:
            raw -= 0x10000
        return round(raw * self.scale, 6)


# --- holding registers: commands and setpoints (FC3 read, FC6/FC16 write) -------

VALVE_COMMAND = Register(
    "VALVE_COMMAND", 0, Table.HOLDING, "glue valve command: 0 closed, 1 open", "", 1, 0, 1
)
FLOW_SETPOINT = Register(
    "FLOW_SETPOINT", 1, Table.HOLDING, "flow rate setpoint", "ml/min", 0.1, 0.0, 1000.0
)
PRESSURE_SETPOINT = Register(
    "PRESSURE_SETPOINT", 2, Table.HOLDING, "supply pressure setpoint", "PSI", 0.1, 0.0, 150.0
)

# --- input registers: feedback and measurements (FC4, read-only) ----------------

VALVE_STATE = Register(
    "VALVE_STATE", 100, Table.INPUT, "valve position feedback: 0 closed, 1 open", "", 1, 0, 1
)
FLOW_SETPOINT_ACTIVE = Register(
    "FLOW_SETPOINT_ACTIVE", 101, Table.INPUT, "flow setpoint in use", "ml/min", 0.1, 0.0, 1000.0
)
PRESSURE_SETPOINT_ACTIVE = Register(
    "PRESSURE_SETPOINT_ACTIVE", 102, Table.INPUT, "pressure setpoint in use", "PSI", 0.1, 0.0, 150.0
)
FLOW_MEASURED = Register(
    "FLOW_MEASURED", 103, Table.INPUT, "measured flow rate", "ml/min", 0.1, 0.0, 1500.0
)
PRESSURE_MEASURED = Register(
    "PRESSURE_MEASURED", 104, Table.INPUT, "measured supply pressure", "PSI", 0.1, 0.0, 300.0
)
TEMPERATURE = Register(
    "TEMPERATURE", 105, Table.INPUT, "glue temperature (signed)", "°C", 0.1, -40.0, 150.0, True
)
ALARM_BITS = Register(
    "ALARM_BITS", 106, Table.INPUT, "active alarms, one bit each (see Alarm)", "bits", 1, 0, 0xFFFF
)
UPTIME = Register(
    "UPTIME",
    107,
    Table.INPUT,
    "seconds since power-up, wraps at 65536 (heartbeat)",
    "s",
    1,
    0,
    0xFFFF,
)

# The totaliser: one 32-bit count of microlitres in two registers, high word first. The
# scales make each word's engineering value a part of the total, so total = high + low.
TOTAL_UNIT_ML = 0.001
DISPENSED_HIGH = Register(
    "DISPENSED_HIGH",
    108,
    Table.INPUT,
    "glue dispensed since power-up, high word (32-bit µl count, wraps)",
    "ml",
    TOTAL_UNIT_ML * 65536,
    0.0,
    TOTAL_UNIT_ML * 65536 * 65535,
)
DISPENSED_LOW = Register(
    "DISPENSED_LOW",
    109,
    Table.INPUT,
    "glue dispensed since power-up, low word",
    "ml",
    TOTAL_UNIT_ML,
    0.0,
    TOTAL_UNIT_ML * 65535,
)
TOTAL_WRAP_ML = TOTAL_UNIT_ML * (1 << 32)
# More than a dispenser at its top flow (1 000 ml/min) gives in a minute between two reads.
TOTAL_WRAP_MARGIN_ML = 1000.0

REGISTERS: tuple[Register, ...] = (
    VALVE_COMMAND,
    FLOW_SETPOINT,
    PRESSURE_SETPOINT,
    VALVE_STATE,
    FLOW_SETPOINT_ACTIVE,
    PRESSURE_SETPOINT_ACTIVE,
    FLOW_MEASURED,
    PRESSURE_MEASURED,
    TEMPERATURE,
    ALARM_BITS,
    UPTIME,
    DISPENSED_HIGH,
    DISPENSED_LOW,
)
HOLDING_REGISTERS = tuple(r for r in REGISTERS if r.table is Table.HOLDING)
INPUT_REGISTERS = tuple(r for r in REGISTERS if r.table is Table.INPUT)

#: The status block: one FC4 read of STATUS_COUNT registers from STATUS_ADDRESS.
STATUS_ADDRESS = VALVE_STATE.address
STATUS_COUNT = len(INPUT_REGISTERS)


class Alarm(IntFlag):
    """Bits of ALARM_BITS. A set bit is an active alarm on the dispenser."""

    LOW_PRESSURE = 1 << 0
    HIGH_PRESSURE = 1 << 1
    OVER_TEMPERATURE = 1 << 2
    NOZZLE_BLOCKED = 1 << 3
    RESERVOIR_LOW = 1 << 4
    VALVE_FAULT = 1 << 5


ALARM_NAMES: tuple[str, ...] = tuple(a.name for a in Alarm if a.name)

MODBUS_EXCEPTIONS: dict[int, str] = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value",
    4: "device failure",
    5: "acknowledge",
    6: "device busy",
    8: "memory parity error",
    10: "gateway path unavailable",
    11: "gateway target failed to respond",
}


def register_by_name(name: str) -> Register:
    """Look a register up by its map name (e.g. "FLOW_SETPOINT")."""
    for register in REGISTERS:
        if register.name == name:
            return register
    raise KeyError(f"no register named {name!r} in the glue register map")


def register_at(table: Table, address: int) -> Register | None:
    """The register at `address` in `table`, or None if the map has none there."""
    for register in REGISTERS:
        if register.table is table and register.address == address:
            return register
    return None


def encode_valve(open_: bool) -> int:
    """VALVE_COMMAND value for open (1) or closed (0)."""
    return 1 if open_ else 0


def encode_flow(ml_min: float) -> int:
    """FLOW_SETPOINT raw value; ValueError outside 0-1000 ml/min."""
    return FLOW_SETPOINT.encode(ml_min)


def encode_pressure(psi: float) -> int:
    """PRESSURE_SETPOINT raw value; ValueError outside 0-150 PSI."""
    return PRESSURE_SETPOINT.encode(psi)


def alarm_names(bits: int) -> tuple[str, ...]:
    """Names of the set alarm bits, lowest bit first; undefined bits read `BIT<n>`.

    Undefined bits are kept rather than dropped: newer firmware may add alarms,
    and an unknown alarm must still stop the cell.
    """
    names: list[str] = []
    for bit in range(16):
        if bits & (1 << bit):
            try:
                names.append(Alarm(1 << bit).name or f"BIT{bit}")
            except ValueError:
                names.append(f"BIT{bit}")
    return tuple(names)


def alarm_bits(names: Iterable[str]) -> int:
    """Bitfield for alarm names (the inverse of `alarm_names`); ValueError on an unknown name."""
    bits = 0
    for name in names:
        if name not in Alarm.__members__:
            raise ValueError(f"unknown glue alarm {name!r}; known: {', '.join(ALARM_NAMES)}")
        bits |= Alarm[name]
    return bits


def encode_dispensed(ml: float) -> tuple[int, int]:
    """The totaliser's two registers (high, low) for `ml` dispensed; the count wraps at 2³²
    µl (about 4 295 l), as the dispenser's does."""
    count = round(ml / TOTAL_UNIT_ML) % (1 << 32)
    return count >> 16, count & 0xFFFF


def dispensed_since(before_ml: float, after_ml: float) -> float:
    """Glue dispensed between two totaliser readings.

    A count that went back wrapped if it was within `TOTAL_WRAP_MARGIN_ML` of its top,
    and otherwise started again from 0 (the dispenser was powered up again): then what
    it counted since is what was dispensed.
    """
    if after_ml >= before_ml:
        return round(after_ml - before_ml, 6)
    if before_ml > TOTAL_WRAP_ML - TOTAL_WRAP_MARGIN_ML:
        return round(after_ml + TOTAL_WRAP_ML - before_ml, 6)
    return after_ml


def exception_text(code: int) -> str:
    """Human wording of a Modbus exception code, for error messages."""
    return f"Modbus exception {code} ({MODBUS_EXCEPTIONS.get(code, 'unknown')})"


def _status_value(registers: Sequence[int], register: Register) -> float:
    return register.decode(registers[register.address - STATUS_ADDRESS])


def decode_status(registers: Sequence[int]) -> GlueStatus:
    """GlueStatus from the STATUS_COUNT input registers read at STATUS_ADDRESS."""
    if len(registers) != STATUS_COUNT:
        raise ValueError(
            f"the glue status block is {STATUS_COUNT} registers from {STATUS_ADDRESS}, "
            f"got {len(registers)}"
        )
    return GlueStatus(
        valve_open=_status_value(registers, VALVE_STATE) != 0,
        flow_setpoint_ml_min=_status_value(registers, FLOW_SETPOINT_ACTIVE),
        pressure_setpoint_psi=_status_value(registers, PRESSURE_SETPOINT_ACTIVE),
        flow_ml_min=_status_value(registers, FLOW_MEASURED),
        pressure_psi=_status_value(registers, PRESSURE_MEASURED),
        temperature_c=_status_value(registers, TEMPERATURE),
        alarms=alarm_names(registers[ALARM_BITS.address - STATUS_ADDRESS]),
        dispensed_ml=round(
            _status_value(registers, DISPENSED_HIGH) + _status_value(registers, DISPENSED_LOW), 6
        ),
    )


def decode_uptime(registers: Sequence[int]) -> int:
    """UPTIME (seconds, wrapping) from the status block; a frozen value means frozen firmware."""
    return registers[UPTIME.address - STATUS_ADDRESS]
