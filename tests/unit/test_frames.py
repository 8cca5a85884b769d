"""The latest-frame holder, and the capture path that fills it (on fakes)."""

from __future__ import annotations

import cv2
import numpy as np

from server.core.operations.base import OperationContext
from server.core.operations.camera_frames import capture, capture_undistorted
from server.core.operations.frames import LatestFrame
from server.settings.model import Settings
from server.storage import CellStores
from tests.fakes import FakeCamera, FakeGlue, FakeRobot


def test_the_newest_frame_replaces_the_one_before_and_is_encoded_once() -> None:
    frames = LatestFrame()
    assert frames.latest is None
    first = frames.keep(np.zeros((1080, 1920, 3), np.uint8), source="trajectory", run_id="a")
    image = np.full((1080, 1920, 3), 200, np.uint8)
    second = frames.keep(image, source="create_workpiece", run_id="b", taken_at=12.5)
    assert frames.latest is second and second.seq == first.seq + 1
    assert (second.width, second.height, second.taken_at) == (1920, 1080, 12.5)
    jpeg = frames.jpeg(second)
    decoded = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert decoded.shape == image.shape and abs(float(decoded.mean()) - 200) < 2
    assert frames.jpeg(second) is jpeg  # cached for the newest frame
    assert frames.jpeg(first) is not jpeg  # an older one is encoded, not mixed up


async def test_undistorted_captures_are_kept_with_their_operation_and_raw_ones_not(
    tmp_path,
) -> None:
    ctx = OperationContext(
        robot=FakeRobot(),
        glue=FakeGlue(),
        camera=FakeCamera(),
        settings=Settings(data_path=tmp_path),
        stores=CellStores.open(tmp_path),
        params={},
        run_id="run-1",
        operation="create_workpiece",
    )
    await capture(ctx, "camera calibration")
    assert ctx.frames.latest is None
    frame = await capture_undistorted(ctx, "workpiece creation")
    kept = ctx.frames.latest
    assert kept is not None and kept.image is frame
    assert (kept.source, kept.run_id) == ("create_workpiece", "run-1")
