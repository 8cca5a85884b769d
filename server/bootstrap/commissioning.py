"""Commission the simulated cell the way a real one is delivered: calibrated,
with one part in the library, so `POST /start` sprays it out of the box.

It runs the cell's own operations (camera calibration, robot calibration,
workpiece creation) on the simulated camera before the state machine starts:
the same vision code, the same stores, nothing hard-coded. It never touches
the robot or the glue, runs only for a simulated camera, only for what the
data directory does not hold yet, and says in the log what it did.
"""

from __future__ import annotations

import logging

from server.common.errors import OperationError
from server.core.operations.base import Operation, OperationContext
from server.core.operations.calibration import calibrate_camera, calibrate_robot
from server.core.operations.workpieces import create_workpiece
from server.core.worker.devices import CellDevices
from server.drivers.camera import SimulatedCamera
from server.drivers.sim.camera_workpieces import DEMO_WORKPIECE
from server.settings.model import Settings
from server.storage import CellStores

log = logging.getLogger(__name__)

DEMO_ID = "demo"
DEMO_BEAD_INSET_MM = -5.0  # the demo part's outline offset: its bead lies inside
# Tries of a step whose frame did not come in time. The image process works a little below
# the server's priority: on a machine busy with other work its first frames can miss their
# bound, and a cell left uncommissioned refuses every start ("the workpiece library is
# empty").
FRAME_TIMEOUT_TRIES = 3


async def commission_simulated_cell(
    devices: CellDevices, stores: CellStores, settings: Settings
) -> list[str]:
    """Bring a fresh simulated cell to a sprayable state; what was done, one line each."""
    camera = devices.camera
    if not isinstance(camera, SimulatedCamera):
        return []
    if not camera.scene.workpieces:
        camera.place_workpiece(*DEMO_WORKPIECE)
    calibration = stores.calibration
    steps: list[tuple[str, Operation, dict]] = []
    if calibration.camera is None:
        steps.append(("camera calibration", calibrate_camera, {}))
    if calibration.camera is None or calibration.robot is None:
        steps.append(("robot calibration", calibrate_robot, {}))
    if not stores.workpieces.list() and not stores.workpieces.exists(DEMO_ID):
        steps.append(
            (
                "workpiece creation",
                create_workpiece,
                {
                    "workpiece_id": DEMO_ID,
                    "name": "Demo part (simulated cell)",
                    # A bead 5 mm in from the edge, where glue goes on a real part: on
                    # the edge it would run off, and hide the edge the camera finds.
                    "spray": {"outline_offset_mm": DEMO_BEAD_INSET_MM},
                },
            )
        )
    if not steps:
        return []
    await camera.connect()
    done = []
    for name, operation, params in steps:
        context = OperationContext(
            robot=devices.robot,
            glue=devices.glue,
            camera=camera,
            settings=settings,
            stores=stores,
            params=params,
        )
        for attempt in range(1, FRAME_TIMEOUT_TRIES + 1):
            try:
                result = await operation(context)
            except OperationError as exc:
                if exc.code == "VISION_TIMEOUT" and attempt < FRAME_TIMEOUT_TRIES:
                    log.warning("simulated cell: %s: %s; trying again", name, exc)
                    continue
                line = f"simulated cell not commissioned: {name} failed: {exc}"
                log.error(line)
            except Exception as exc:  # the cell starts anyway: a person can run the step later
                line = f"simulated cell not commissioned: {name} failed: {exc}"
                log.error(line)
            else:
                line = f"simulated cell commissioned: {name}: {result.as_dict()}"
                log.info(line)
            break
        done.append(line)
    return done
