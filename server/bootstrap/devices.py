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
from server.settings.model import Settings, parse_tcp_address

log = logging.getLogger(__name__)


def glue_supervision(settings: Settings) -> dict[str, Any]:
    """The dispenser driver's supervision options from the settings (docs/hardware.md)."""
    return {
        "poll_interval": settings.glue_poll_interval,
        "pressure_range_psi": settings.glue_pressure_range_psi,
        "flow_tolerance_pct": settings.glue_flow_deviation_pct,
        "flow_deviation_s": settings.glue_flow_deviation_s,
        "temperature_range_c": settings.glue_temperature_range_c,
        "link_timeout": settings.glue_link_timeout,
    }


async def build_devices(
    settings: Settings,
) -> tuple[CellDevices, Callable[[], Awaitable[None]]]:
    """The three device clients, plus a function that releases what was started for them."""
    host = None
    if settings.robot_simulated or settings.glue_simulated:
        from server.drivers.sim.host import SimulatorHost

        host = SimulatorHost(settings)
        await asyncio.to_thread(host.start)

    if settings.robot_simulated:
        assert host is not None and host.robot is not None
        robot_address = ("127.0.0.1", host.robot.port)
        log.info("robot: simulator on 127.0.0.1:%d", host.robot.port)
    else:
        robot_address = (settings.robot_ip, settings.robot_port)
    robot = JsonRpcRobot(
        *robot_address,
        timeout=settings.robot_communication_timeout,
        heartbeat_interval=settings.robot_heartbeat_interval,
    )

    port = settings.glue_controller_port
    supervision = glue_supervision(settings)
    if settings.glue_simulated:
        assert host is not None and host.glue is not None
        glue = ModbusGlueDispenser.tcp(
            "127.0.0.1",
            host.glue.port,
            device_id=settings.glue_modbus_device_id,
            timeout=settings.glue_system_timeout,
            **supervision,
        )
        log.info("glue: simulator on 127.0.0.1:%d (Modbus RTU over TCP)", host.glue.port)
    elif port.startswith("tcp://"):
        glue = ModbusGlueDispenser.tcp(
            *parse_tcp_address(port),
            device_id=settings.glue_modbus_device_id,
            timeout=settings.glue_system_timeout,
            **supervision,
        )
    else:
        glue = ModbusGlueDispenser.serial(
            port,
            device_id=settings.glue_modbus_device_id,
            timeout=settings.glue_system_timeout,
            **supervision,
        )

    camera_id = settings.vision_camera_id
    camera: SimulatedCamera | OpenCVCamera
    if settings.camera_simulated:
        # The simulated table is printed from the configured layout, so the settings the
        # robot calibration checks against describe the table it sees.
        scene = Scene.printed(settings.marker_positions_mm, settings.marker_size_mm)
        camera = SimulatedCamera(scene, timeout=settings.vision_processing_timeout)
        if host is not None and host.robot is not None and host.glue is not None:
            # The camera shows the glue the simulators dispensed. With either simulator out
            # of process (or a real device) it has no record of it and shows no bead.
            camera.bead_source = dispensed_by(host.robot, host.glue)
    else:
        source: int | str = int(camera_id) if camera_id.isdigit() else camera_id
        camera = OpenCVCamera(source, timeout=settings.vision_processing_timeout)

    async def release() -> None:
        if host is not None:
            await asyncio.to_thread(host.stop)

    return CellDevices(robot, glue, camera), release
