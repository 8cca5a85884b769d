"""The narrow interfaces the core uses to reach the cell's three devices.

The core never knows whether it talks to real hardware, to a network
simulator, or to an in-process fake: it sees only these Protocols. Each
production client speaks the device's real protocol (JSON-RPC/TCP for the
robot, Modbus RTU for the glue dispenser, OpenCV for the camera).

Drivers report faults they discover on their own (a dropped connection, a
dispenser alarm) through a `FaultListener`, so the machine can go to ERROR
without waiting for the next command to fail.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple, Protocol, runtime_checkable

import numpy as np


class Pose(NamedTuple):
    """Tool pose in the robot base frame: millimetres and degrees."""

    x: float
    y: float
    z: float
    rx: float = 180.0
    ry: float = 0.0
    rz: float = 0.0

    @classmethod
    def from_sequence(cls, values: Sequence[float]) -> Pose:
        """Build a pose from the wire format `[x, y, z, rx, ry, rz]`."""
        if len(values) != 6:
            raise ValueError(f"a pose has 6 values [x, y, z, rx, ry, rz], got {len(values)}")
        return cls(*(float(v) for v in values))


@dataclass(frozen=True)
class DeviceFault:
    """A fault a driver found by itself, outside any command."""

    device: str  # "robot", "glue" or "camera"
    code: str  # stable identifier, e.g. "COMM_LOST", "ALARM"
    message: str  # what a technician should read


FaultListener = Callable[[DeviceFault], None]


@dataclass
class DeviceHealth:
    """What GET /health shows for one device."""

    name: str
    connected: bool = False
    last_rtt_ms: float | None = None
    last_error: str | None = None
    last_ok_at: float | None = None
    details: dict[str, Any] = field(default_factory=dict)
    # Conditions the device's own monitoring sees persisting right now (an alarm
    # bit, a pressure outside its window): what "is a reset allowed now?" can
    # tell without a probe. A reset still probes live before it is accepted.
    active_faults: tuple[str, ...] = ()

    def record_ok(self, rtt_s: float) -> None:
        """Note a successful exchange and its round-trip time."""
        self.connected = True
        self.last_rtt_ms = round(rtt_s * 1000.0, 3)
        self.last_ok_at = time.time()

    def record_error(self, message: str, *, connected: bool | None = None) -> None:
        """Note a failed exchange; `connected` is updated only when given."""
        self.last_error = message
        if connected is not None:
            self.connected = connected


@dataclass(frozen=True)
class GlueStatus:
    """One reading of the glue dispenser (engineering units)."""

    valve_open: bool
    flow_setpoint_ml_min: float
    pressure_setpoint_psi: float
    flow_ml_min: float
    pressure_psi: float
    temperature_c: float
    alarms: tuple[str, ...] = ()
    # The dispenser's totaliser (ml since its power-up, wrapping; glue_registers.py):
    # None from a dispenser that keeps none.
    dispensed_ml: float | None = None


@runtime_checkable
class Robot(Protocol):
    """A six-axis arm that follows linear moves and can be stopped at any time."""

    health: DeviceHealth

    async def connect(self) -> None:
        """Open the link; raise DeviceError if the controller does not answer."""

    async def close(self) -> None:
        """Close the link; never raises."""

    async def move_linear(self, pose: Pose, speed: float, acceleration: float) -> None:
        """Move in a straight line (mm/s, mm/s²); return once the pose is reached.

        Cancelling the awaiting task stops the arm.
        """

    async def move_joint(self, target: Pose, speed: float) -> None:
        """Move by joint interpolation (deg/s); return once the pose is reached."""

    async def get_position(self) -> Pose:
        """The tool pose now."""

    async def is_moving(self) -> bool:
        """True while a commanded motion is under way."""

    async def stop(self) -> None:
        """Stop motion at once. Must get through while a move is in progress."""

    def new_session(self) -> int:
        """Begin a new link session (a reset does) and return its number.

        A request sent before it may still end, but its timeout or late answer
        no longer reports a fault or changes `health`: what the device did
        before a reset must not fault the cell after it.
        """

    def set_fault_listener(self, listener: FaultListener | None) -> None:
        """Where to report faults found outside a command (e.g. connection lost)."""


@runtime_checkable
class GlueDispenser(Protocol):
    """A dispenser with one valve, a flow setpoint and a pressure setpoint."""

    health: DeviceHealth
    pressure_range_psi: tuple[float, float]  # measured pressure outside it is a fault

    async def connect(self) -> None:
        """Open the link; raise DeviceError if the dispenser does not answer."""

    async def close(self) -> None:
        """Close the link; never raises."""

    async def set_valve(self, open_: bool) -> None:
        """Open or close the glue valve."""

    async def set_flow_rate(self, ml_per_min: float) -> None:
        """Set the flow setpoint in ml/min."""

    async def set_pressure(self, psi: float) -> None:
        """Set the pressure setpoint in PSI."""

    def drop_waiting_openings(self) -> int:
        """Refuse every valve opening not yet sent (its call raises CancelledError); how many.

        A close goes ahead of commands waiting for the dispenser: an opening asked
        for before a halt must not go out after the halt's close.
        """

    async def read_status(self) -> GlueStatus:
        """Valve, setpoints, measured flow, pressure, temperature and alarms."""

    def new_session(self) -> int:
        """Begin a new link session (a reset does) and return its number.

        A request sent before it may still end, but its timeout or late answer
        no longer reports a fault or changes `health`: what the device did
        before a reset must not fault the cell after it.
        """

    def set_fault_listener(self, listener: FaultListener | None) -> None:
        """Where to report faults found outside a command (e.g. alarm bit, silence)."""


@runtime_checkable
class Camera(Protocol):
    """A camera looking down on the work table."""

    health: DeviceHealth

    async def connect(self) -> None:
        """Open the camera; raise DeviceError if it cannot deliver a frame."""

    async def close(self) -> None:
        """Release the camera; never raises."""

    async def capture(self) -> np.ndarray:
        """One BGR frame (uint8, H×W×3)."""

    def set_fault_listener(self, listener: FaultListener | None) -> None:
        """Where to report faults found outside a command."""
