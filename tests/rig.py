"""Tier two with real protocols: the cell server in this test's loop, reaching the
robot and glue simulators (also in this loop) through its production clients,
and the simulated camera in-process, so tests can move parts on the table and
inject faults.

`DEVICE_FAULTS` names each fault the simulators can inject, with what the cell
is expected to do about it, so the random-point fault test and the soak inject
and judge faults the same way; `assert_safe` is the check every fault test shares."""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx

from server.bootstrap.cell import Cell
from server.bootstrap.devices import build_devices
from server.core.worker.devices import CellDevices
from server.drivers.camera import SimulatedCamera
from server.drivers.sim.camera_bead import dispensed_by
from server.drivers.sim.glue_sim import GlueSimulator
from server.drivers.sim.robot_sim import RobotSimulator
from server.settings.model import Settings
from server.storage.journal import records
from tests.commissioned import Template, commissionable, continue_noise, seed_commissioned
from tests.serving import admin_headers, serve

SPRAY_DEMO = {"contour_matching": False, "workpiece_id": "demo"}
# The rig's device timeouts: robot_communication_timeout and glue_system_timeout, and
# the glue link's. Short, so a stalled device is found in seconds; yet several times
# the longest stall of this process's event loop (which runs the test, the server and
# both simulators) seen with both cores kept busy by other processes (`make
# test-loaded`: hundreds of milliseconds). A timeout within reach of such a stall turns
# load into a spurious device fault: at 1 s, a robot never stalled went NO_ANSWER.
TIMEOUT = 3.0
GLUE_LINK_TIMEOUT = 1.5  # glue_link_timeout (0.5 s by default): a silent dispenser
# The rig's vision_processing_timeout: no test waits for it to fire (a stalled camera is
# cleared by the test), so it only bounds a frame or a solve. Under pytest-xdist the other
# worker renders and solves frames at the same time on the same cores, where a robot
# calibration that takes a second alone can take ten.
VISION_TIMEOUT = 30.0
# Bounds on what the test waits for (the server up, a state reached): never performance
# assertions, so generous enough for a machine that is busy with something else.
WAIT_S = 60.0


@dataclass
class Rig:
    api: httpx.AsyncClient
    cell: Cell
    robot: RobotSimulator
    glue: GlueSimulator

    @property
    def camera(self) -> SimulatedCamera:
        return self.cell.devices.camera  # type: ignore[return-value]

    async def state(self) -> dict:
        return (await self.api.get("/state")).json()

    async def wait_state(self, state: str, timeout: float = WAIT_S) -> dict:
        async with asyncio.timeout(timeout):
            while (snapshot := await self.state())["state"] != state:
                await asyncio.sleep(0.01)
        return snapshot

    async def start_spraying(self) -> None:
        assert (await self.api.post("/start", json=SPRAY_DEMO)).status_code == 202
        async with asyncio.timeout(WAIT_S):
            while not self.glue.valve_open:
                await asyncio.sleep(0.005)

    async def begin(self, operation: str) -> None:
        """Start `operation`: "spray" (returns once glue flows) or a command such as
        "calibrate-camera" (returns once accepted)."""
        if operation == "spray":
            await self.start_spraying()
            return
        response = await self.api.post(f"/{operation}")
        assert response.status_code == 202, response.json()

    async def reset(self) -> httpx.Response:
        return await self.api.post("/reset")


async def run(rig: Rig, command: str, body: dict | None = None) -> dict:
    """Send a command, wait for the operation to end; the final state snapshot."""
    response = await rig.api.post(f"/{command}", json=body)
    assert response.status_code == 202, response.text
    async with asyncio.timeout(WAIT_S):
        while (snapshot := await rig.state())["state"] not in ("IDLE", "ERROR"):
            await asyncio.sleep(0.02)
    return snapshot


async def append_inspected_run(rig: Rig, run_id: str, inspection: dict[str, Any]) -> None:
    """An inspected spray run's start and end (its result carrying `inspection`, the
    inspection's summary), written through the cell's own journal writer: a part on record without
    spraying it."""
    journal = rig.cell.journal
    assert journal is not None
    now = time.time()
    result = {"workpieces": ["demo"], "waypoints": 9, "inspection": inspection}
    written = journal.append(
        [
            records.operation_started(run_id, "trajectory", now - 2, {"workpiece_id": "demo"}),
            records.operation_ended(run_id, now - 1, "completed", result, None, 1),
        ]
    )
    assert written is not None
    await written


async def assert_safe(rig: Rig, component: str) -> dict:
    """ERROR, the fault named, the valve closed and the robot still."""
    snapshot = await rig.wait_state("ERROR", timeout=TIMEOUT * 3 + 5)
    assert snapshot["stop_reason"]["component"] == component, snapshot
    async with asyncio.timeout(TIMEOUT * 3):
        while rig.robot.is_moving:
            await asyncio.sleep(0.01)
    return snapshot


@dataclass(frozen=True)
class DeviceFaultKind:
    """A fault the simulators inject, and what the cell must do about it."""

    name: str
    component: str  # the device the stop reason must name
    codes: frozenset[str]  # the stop-reason codes it may cause (first fault out)
    refusal: str  # what a reset refused while the fault lasts says
    operation: str  # the operation it interrupts (see Rig.begin)
    inject: Callable[[Rig], None]
    clear: Callable[[Rig], None]
    # The drivers notice it with nothing to do (a lost link, the dispenser monitor);
    # otherwise it shows at the next use of the device.
    noticed_when_idle: bool = True
    # The dispenser still takes commands, so the halt closes the valve at once; a silent
    # one cannot be told, and the valve is closed again by the reset.
    valve_closes_at_once: bool = True
    # The robot link is up, so the halt's stop reaches the controller.
    stop_reaches_robot: bool = True


# How long a dropped robot refuses reconnection: until the test clears the fault, which
# it always does first (this only ends a forgotten one). A window that ran out by
# itself would race the test's refused reset on a busy machine.
DROP_REFUSAL_S = WAIT_S

DEVICE_FAULTS: dict[str, DeviceFaultKind] = {
    kind.name: kind
    for kind in (
        DeviceFaultKind(
            "robot-dropped",
            "robot",
            frozenset({"COMM_LOST"}),
            "robot",
            "spray",
            lambda rig: rig.robot.inject_fault("drop", duration=DROP_REFUSAL_S),
            lambda rig: rig.robot.clear_faults(),
            stop_reaches_robot=False,
        ),
        DeviceFaultKind(
            "robot-stalled",
            "robot",
            # The heartbeat notices it when idle (NO_ANSWER); a move running into it
            # fails first (DEVICE_FAULT), or the homing move does.
            frozenset({"DEVICE_FAULT", "SAFE_POSITION_FAILED", "NO_ANSWER"}),
            "robot: no answer",
            "spray",
            lambda rig: rig.robot.inject_fault("stall"),
            lambda rig: rig.robot.clear_faults(),
        ),
        DeviceFaultKind(
            "dispenser-silent",
            "glue",
            # Silent while the valve may be open: VALVE_UNCONFIRMED within glue_link_timeout.
            frozenset({"VALVE_UNCONFIRMED", "NO_REPLY", "DEVICE_FAULT"}),
            "glue",
            "spray",
            lambda rig: rig.glue.inject_no_reply(),
            lambda rig: rig.glue.clear_faults(),
            valve_closes_at_once=False,
        ),
        DeviceFaultKind(
            "dispenser-alarm",
            "glue",
            frozenset({"ALARM"}),
            "glue: alarm NOZZLE_BLOCKED",
            "spray",
            lambda rig: rig.glue.set_alarm("NOZZLE_BLOCKED"),
            lambda rig: rig.glue.clear_faults(),
        ),
        DeviceFaultKind(
            "dispenser-pressure",
            "glue",
            frozenset({"PRESSURE_OUT_OF_RANGE"}),
            "outside",
            "spray",
            lambda rig: rig.glue.force_pressure(180.0),
            lambda rig: rig.glue.clear_faults(),
        ),
        DeviceFaultKind(
            "camera-failed",
            "camera",
            frozenset({"CAPTURE_FAILED", "DEVICE_FAULT"}),
            "camera",
            "calibrate-camera",
            lambda rig: rig.camera.inject_fault("fail"),
            lambda rig: rig.camera.clear_faults(),
            noticed_when_idle=False,
        ),
    )
}


@contextlib.asynccontextmanager
async def open_rig(
    data_path,
    *,
    port: int | None = None,
    camera_stalled: bool = False,
    robot_speed_factor: float = 4,
    glue_speed_factor: float = 1,
    wait_idle: bool = True,
    **overrides: Any,
) -> AsyncIterator[Rig]:
    """Simulators, cell and HTTP client; the cell commissioned in `data_path`.

    A fresh `data_path` gets a copy of a cell commissioned once per test process with
    the same settings (tests/commissioned.py), which is what the cell would have
    written commissioning itself; one that holds anything is used as it is.
    `overrides` replace any setting, the rig's timeouts included. `port`: the server's
    (a free one by default). `camera_stalled`: the simulated camera stalls from the
    start, so the cell stays INITIALIZING (for up to vision_processing_timeout) until the
    test calls `rig.camera.clear_faults()`; the rig then does not wait for IDLE. Only for
    a data directory commissioned already: commissioning needs the camera.
    `robot_speed_factor`: the robot simulator's (4: fast tests; 1: moves take the time the
    plan says, as a real arm's, for what measures the run against its plan).
    `glue_speed_factor`: the glue simulator's (1: its dynamics at their own pace; the
    robot's factor: both as the served simulated cell runs them). `wait_idle`
    False: yield as soon as the server answers (a restart after an interruption comes
    up in ERROR)."""
    async with (
        RobotSimulator(speed_factor=robot_speed_factor) as robot,
        GlueSimulator(speed_factor=glue_speed_factor) as glue,
    ):
        defaults: dict[str, Any] = {
            "robot_communication_timeout": TIMEOUT,
            "glue_system_timeout": TIMEOUT,
            "glue_link_timeout": GLUE_LINK_TIMEOUT,
            "reset_probe_timeout": TIMEOUT * 2,  # a probe renders a camera frame too
            "emergency_stop_timeout": 0.5,
            "vision_processing_timeout": VISION_TIMEOUT,
            # No report at a shift's end in the middle of a test that counts notices and
            # messages: a test of the reports makes its own (test_shift_reports.py).
            "shift_reports": False,
            # This test process holds many cells and tests: its memory is not one cell's, so
            # the memory limit is not watched unless a test sets it (test_self_watch.py).
            "memory_limit": None,
        }
        settings = Settings(
            robot_ip="127.0.0.1",
            robot_port=robot.port,
            glue_controller_port=f"tcp://127.0.0.1:{glue.port}",
            data_path=data_path,
            **{**defaults, **overrides},
        )
        template = None
        if not camera_stalled and commissionable(settings, Path(data_path)):
            template = await seed_commissioned(settings)
        cell = Cell(settings, device_factory=_devices_seeing(robot, glue, camera_stalled, template))
        async with (
            serve(cell, port) as url,
            httpx.AsyncClient(
                base_url=url,
                timeout=WAIT_S,
                headers=admin_headers(data_path),
                # An idle connection is let go well before the server closes it
                # (http_keepalive_timeout): at the same 5 s on both ends, a request sent
                # as the server closes the connection fails with ReadError.
                limits=httpx.Limits(keepalive_expiry=settings.http_keepalive_timeout / 2),
            ) as api,
        ):
            rig = Rig(api, cell, robot, glue)
            if not camera_stalled and wait_idle:
                await rig.wait_state("IDLE")
            yield rig


def _devices_seeing(
    robot: RobotSimulator, glue: GlueSimulator, stalled: bool, template: Template | None
) -> Callable[[Settings], Awaitable[tuple[CellDevices, Callable[[], Awaitable[None]]]]]:
    """The default devices; the simulated camera sees the bead the rig's simulators lay.

    The rig's simulators run in the test's process, as the default run's do in the
    server's, so the camera is wired to them the same way (server/bootstrap/devices.py).
    `stalled`: the camera stalls before the cell opens it. `template`: the commissioned
    cell the data directory was copied from, whose camera's noise this one continues.
    """

    async def build(settings: Settings) -> tuple[CellDevices, Callable[[], Awaitable[None]]]:
        devices, release = await build_devices(settings)
        assert isinstance(devices.camera, SimulatedCamera)
        devices.camera.bead_source = dispensed_by(robot, glue)
        glue.speed_source = robot  # as server/drivers/sim/host.py wires it
        if template is not None:
            continue_noise(devices.camera, template)
        if stalled:
            devices.camera.inject_fault("stall")
        return devices, release

    return build
