"""The simulated cell commissions itself even when a frame misses its bound.

The image process renders below the server's priority: on a machine busy with other
work its first frames can take longer than vision_processing_timeout. A cell whose
commissioning gave up on that started uncommissioned, with no calibration and an
empty library, and refused every start ("the workpiece library is empty"). Here
the real simulated camera and image process are used, and the camera's first frame
is held past the bound, as a starved image process holds it.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np

from server.bootstrap.commissioning import DEMO_ID, commission_simulated_cell
from server.core.worker.devices import CellDevices
from server.drivers.camera import SimulatedCamera
from server.drivers.sim.camera_scene import Scene
from server.settings.model import Settings
from server.storage import CellStores
from tests.fakes import FakeGlue, FakeRobot

FRAME_BOUND_S = 5.0  # the cell's default vision_processing_timeout


class StarvedCamera(SimulatedCamera):
    """The simulated camera, whose first frame comes only after the bound has passed."""

    held = 1

    async def capture(self) -> np.ndarray:
        if self.held:
            self.held -= 1
            await asyncio.sleep(FRAME_BOUND_S * 10)
        return await super().capture()


async def test_a_frame_late_once_still_commissions_the_cell(tmp_path: Path) -> None:
    settings = Settings(data_path=tmp_path, vision_processing_timeout=FRAME_BOUND_S)
    scene = Scene.printed(settings.marker_positions_mm, settings.marker_size_mm)
    camera = StarvedCamera(scene, timeout=60.0)
    stores = CellStores.open(tmp_path)
    try:
        done = await commission_simulated_cell(
            CellDevices(FakeRobot(), FakeGlue(), camera),  # type: ignore[arg-type]
            stores,
            settings,
        )
    finally:
        await camera.close()
    assert camera.held == 0, "the camera's first frame was never asked for"
    assert all(" commissioned: " in line for line in done), done
    assert stores.calibration.camera is not None and stores.calibration.robot is not None
    assert stores.workpieces.exists(DEMO_ID) and not stores.workpieces.is_empty()
