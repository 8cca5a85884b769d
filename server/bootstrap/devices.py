"""Build the cell's devices from the settings: real hardware or simulators.

Each device is chosen on its own, by its address:

* robot: `ROBOT_IP` = `sim` (default) or the controller's address; port `robot_port` (30003).
* glue: `GLUE_CONTROLLER_PORT` = `sim` (default), a serial device such as
  `/dev/ttyUSB0` (RS-485, 115200 8N1, Modbus RTU), or `tcp://host:port` for an
  RS-485-to-Ethernet gateway in transparent mode (RTU frames over TCP).
* camera: `VISION_CAMERA_ID` = `sim` (default), an OpenCV camera index (`0`)
  or a device path / stream URL. The simulated camera shows the glue bead the
  robot and glue simulators dispensed when both run here (in-process); with
  either one out of process or real, it shows the parts without a bead.

`sim` starts that device's simulator on loopback and talks to it through the
same production client a real device gets, so the default run exercises the
real protocol code.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable
from typing import Any

from server.core.worker.devices import CellDevices
from server.drivers.camera import OpenCVCamera, SimulatedCamera
from server.drivers.glue_modbus import ModbusGlueDispenser
from server.drivers.robot_jsonrpc import JsonRpcRobot
from server.drivers.sim.camera_bead import dispensed_by
from server.drivers.sim.camera_scene import Scene
from server.settings.calibration import CalibrationSettings
from server.settings.camera import CameraSettings
from server.settings.glue import GlueSettings, parse_tcp_address
from server.settings.model import Settings
from server.settings.robot import RobotSettings

log = logging.getLogger(__name__)


def glue_supervision(glue: GlueSettings) -> dict[str, Any]:
    """The dispenser driver's supervision options from the settings (docs/hardware.md)."""
    return {
        "poll_interval": glue.glue_poll_interval,
        "pressure_range_psi": glue.glue_pressure_range_psi,
        "flow_tolerance_pct": glue.glue_flow_deviation_pct,
        "flow_deviation_s": glue.glue_flow_deviation_s,
        "temperature_range_c": glue.glue_temperature_range_c,
        "link_timeout": glue.glue_link_timeout,
    }


async def build_devices(
    settings: Settings,
) -> tuple[CellDevices, Callable[[], Awaitable[None]]]:
    """The three device clients, plus a function that releases what was started for them.

    Each device is built from its own settings section; the simulators, when any device
    is `sim`, from the whole settings (they play the cell: its geometry, its speed).
    """
    robot_settings = settings.section(RobotSettings)
    glue_settings = settings.section(GlueSettings)
    host = None
    if robot_settings.robot_simulated or glue_settings.glue_simulated:
        from server.drivers.sim.host import SimulatorHost

        host = SimulatorHost(settings)
        await asyncio.to_thread(host.start)
    robot = robot_of(robot_settings, host.robot.port if host and host.robot else None)
    glue = glue_of(glue_settings, host.glue.port if host and host.glue else None)
    camera = camera_of(settings.section(CameraSettings), settings.section(CalibrationSettings))
    if (
        isinstance(camera, SimulatedCamera)
        and host is not None
        and host.robot is not None
        and host.glue is not None
    ):
        # The camera shows the glue the simulators dispensed. With either simulator out
        # of process (or a real device) it has no record of it and shows no bead.
        camera.bead_source = dispensed_by(host.robot, host.glue)

    async def release() -> None:
        if host is not None:
            await asyncio.to_thread(host.stop)

    return CellDevices(robot, glue, camera), release


def robot_of(settings: RobotSettings, simulator_port: int | None) -> JsonRpcRobot:
    """The robot's client: to the simulator's port on loopback when `sim`."""
    if settings.robot_simulated:
        assert simulator_port is not None
        address = ("127.0.0.1", simulator_port)
        log.info("robot: simulator on 127.0.0.1:%d", simulator_port)
    else:
        address = (settings.robot_ip, settings.robot_port)
    return JsonRpcRobot(
        *address,
        timeout=settings.robot_communication_timeout,
        heartbeat_interval=settings.robot_heartbeat_interval,
    )


def glue_of(settings: GlueSettings, simulator_port: int | None) -> ModbusGlueDispenser:
    """The dispenser's client: Modbus RTU over TCP (the simulator, a gateway) or serial."""
    port = settings.glue_controller_port
    options: dict[str, Any] = {
        "device_id": settings.glue_modbus_device_id,
        "timeout": settings.glue_system_timeout,
        **glue_supervision(settings),
    }
    if settings.glue_simulated:
        assert simulator_port is not None
        log.info("glue: simulator on 127.0.0.1:%d (Modbus RTU over TCP)", simulator_port)
        return ModbusGlueDispenser.tcp("127.0.0.1", simulator_port, **options)
    if port.startswith("tcp://"):
        return ModbusGlueDispenser.tcp(*parse_tcp_address(port), **options)
    return ModbusGlueDispenser.serial(port, **options)


def camera_of(
    settings: CameraSettings, calibration: CalibrationSettings
) -> SimulatedCamera | OpenCVCamera:
    """The camera's client; the simulated one shows a table printed from the configured
    marker layout, so the settings the robot calibration checks against describe the
    table it sees."""
    if settings.camera_simulated:
        scene = Scene.printed(calibration.marker_positions_mm, calibration.marker_size_mm)
        return SimulatedCamera(scene, timeout=settings.vision_processing_timeout)
    camera_id = settings.vision_camera_id
    source: int | str = int(camera_id) if camera_id.isdigit() else camera_id
    return OpenCVCamera(source, timeout=settings.vision_processing_timeout)
