"""The camera drivers as the core sees them: frames, chessboard cycling, faults, timeouts."""

from __future__ import annotations

import asyncio
import time

import cv2
import numpy as np
import pytest

from server.common.errors import DeviceDisconnected, DeviceError, DeviceTimeout
from server.drivers.base import Camera, DeviceFault
from server.drivers.camera import OpenCVCamera, SimulatedCamera
from server.drivers.sim.camera_scene import chessboard_corner_pixels


def test_both_cameras_implement_the_protocol() -> None:
    assert isinstance(SimulatedCamera(), Camera)
    assert isinstance(OpenCVCamera(0, timeout=1.0), Camera)


async def test_simulated_capture_gives_a_full_hd_bgr_frame() -> None:
    camera = SimulatedCamera(seed=3)
    with pytest.raises(DeviceDisconnected, match="connect"):
        await camera.capture()
    await camera.connect()
    first = await camera.capture()
    second = await camera.capture()
    assert first.shape == (1080, 1920, 3) and first.dtype == np.uint8
    assert not np.array_equal(first, second)  # fresh sensor noise per frame
    assert np.abs(first.astype(np.int16) - second).mean() < 4  # ...of the same scene
    assert camera.health.connected and camera.health.last_rtt_ms is not None
    assert camera.health.details["resolution"] == "1920x1080"
    await camera.close()
    assert not camera.health.connected


async def test_placed_workpiece_appears_where_the_model_says() -> None:
    camera = SimulatedCamera()
    await camera.connect()
    piece = camera.place_workpiece("hexagon", 640.0, 0.0, 10.0)
    frame = await camera.capture()
    u, v = np.rint(camera.model.table_to_pixel(piece.centroid_table_mm())).astype(int)
    assert frame[v, u].mean() > 150  # bright aluminium on the dark table
    camera.clear_workpieces()
    assert (await camera.capture())[v, u].mean() < 100
    await camera.close()


async def test_a_table_drawn_ahead_gives_the_frame_a_capture_gives_without() -> None:
    # Drawn ahead, only the caches change: the capture after it is the very frame (its
    # noise too) of a camera that did not draw ahead, and a table changed since shows.
    ahead, plain = SimulatedCamera(seed=7), SimulatedCamera(seed=7)
    for camera in (ahead, plain):
        await camera.connect()
        await camera.warmed_up()
    await ahead.draw_ahead()
    assert np.array_equal(await ahead.capture(), await plain.capture())
    await ahead.draw_ahead()
    for camera in (ahead, plain):
        piece = camera.place_workpiece("hexagon", 640.0, 0.0, 10.0)
    frame = await ahead.capture()
    assert np.array_equal(frame, await plain.capture())
    u, v = np.rint(ahead.model.table_to_pixel(piece.centroid_table_mm())).astype(int)
    assert frame[v, u].mean() > 150  # the part placed after the drawing ahead
    for camera in (ahead, plain):
        await camera.close()


async def test_chessboard_mode_shows_a_new_pose_per_capture_and_cycles() -> None:
    camera = SimulatedCamera()
    await camera.connect()
    camera.show_chessboard()
    poses = camera.chessboard_poses
    board = camera.chessboard
    seen = []
    for _ in range(len(poses) + 1):
        frame = await camera.capture()
        seen.append(camera.last_chessboard_pose)
    assert seen[: len(poses)] == list(poses)
    assert seen[-1] == poses[0]  # wrapped round
    # the last frame really shows the pose it claims
    grey = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    ok, corners = cv2.findChessboardCorners(grey, board.pattern_size)
    assert ok
    truth = chessboard_corner_pixels(camera.model, board, poses[0])
    corners = corners.reshape(-1, 2)
    error = min(np.abs(corners - truth).max(), np.abs(corners[::-1] - truth).max())
    assert error < 1.0  # integer-level detection, before cornerSubPix
    camera.show_table()
    assert camera.mode == "table"
    await camera.close()


async def test_injected_failure_raises_and_reports_once_per_outage() -> None:
    camera = SimulatedCamera()
    faults: list[DeviceFault] = []
    camera.set_fault_listener(faults.append)
    await camera.connect()
    camera.inject_fault("fail")
    with pytest.raises(DeviceError, match="injected"):
        await camera.capture()
    assert len(faults) == 1
    assert faults[0].device == "camera" and faults[0].code == "CAPTURE_FAILED"
    with pytest.raises(DeviceError):
        await camera.capture()
    assert len(faults) == 1  # still the same outage
    assert "injected" in (camera.health.last_error or "")
    camera.clear_faults()
    await camera.capture()
    camera.inject_fault("fail")
    with pytest.raises(DeviceError):
        await camera.capture()
    assert len(faults) == 2  # a new outage after a good frame
    await camera.close()


async def test_stalled_capture_times_out_within_the_timeout() -> None:
    camera = SimulatedCamera(timeout=0.3)
    faults: list[DeviceFault] = []
    camera.set_fault_listener(faults.append)
    await camera.connect()
    camera.inject_fault("stall")
    started = time.monotonic()
    with pytest.raises(DeviceTimeout, match=r"within 0\.3 s"):
        await camera.capture()
    elapsed = time.monotonic() - started
    # It ended at its timeout, not at the stall's end (there is none): the upper bound only
    # tells the two apart, on a machine as busy as it may be (seconds, under load).
    assert 0.25 <= elapsed < 10.0
    assert not camera.health.connected
    assert [f.code for f in faults] == ["NO_REPLY"]
    camera.clear_faults()
    camera.timeout = 10.0  # a loaded machine may render slowly; only the stall was under test
    await camera.capture()
    assert camera.health.connected
    await camera.close()


async def test_clearing_a_stall_lets_the_waiting_capture_deliver() -> None:
    camera = SimulatedCamera(timeout=10.0)
    await camera.connect()
    camera.inject_fault("stall")
    pending = asyncio.create_task(camera.capture())
    await asyncio.sleep(0.05)
    assert not pending.done()
    camera.clear_faults()
    frame = await asyncio.wait_for(pending, 10.0)
    assert frame.shape == (1080, 1920, 3)
    await camera.close()


async def test_simulated_connect_honours_injected_faults() -> None:
    camera = SimulatedCamera(timeout=0.2)
    camera.inject_fault("fail")
    with pytest.raises(DeviceError):
        await camera.connect()
    camera.inject_fault("stall")
    with pytest.raises(DeviceTimeout):
        await camera.connect()
    assert not camera.health.connected
    with pytest.raises(ValueError, match="unknown camera fault"):
        camera.inject_fault("explode")  # type: ignore[arg-type]


async def test_missing_real_camera_is_reported_as_disconnected_quickly() -> None:
    camera = OpenCVCamera(99, timeout=5.0)
    started = time.monotonic()
    with pytest.raises(DeviceDisconnected, match="camera 99 could not be opened: check the USB"):
        await camera.connect()
    assert time.monotonic() - started < 5.0  # refused, not timed out
    assert camera.health.connected is False
    assert "could not be opened" in (camera.health.last_error or "")
    with pytest.raises(DeviceDisconnected, match="not open"):
        await camera.capture()
    await camera.close()  # never raises, even when never opened


async def test_real_camera_id_from_settings_string_means_an_index() -> None:
    camera = OpenCVCamera("98", timeout=5.0)
    with pytest.raises(DeviceDisconnected, match="camera 98"):
        await camera.connect()


async def test_the_simulated_camera_connects_before_its_first_frame_is_drawn() -> None:
    """Its first frame (the render caches, a second or two) is drawn after connect, in the
    background; the first capture waits for it, then gives its own frame."""
    camera = SimulatedCamera(timeout=5)
    drawing = camera._render
    go_on = asyncio.Event()
    drawn: list[bool] = []

    async def held(*, advance: bool) -> np.ndarray:
        await go_on.wait()
        frame = await drawing(advance=advance)
        drawn.append(advance)
        return frame

    camera._render = held  # type: ignore[method-assign]
    try:
        await asyncio.wait_for(camera.connect(), 60)  # a bound, not a figure
        assert camera.health.connected
        assert drawn == [], "connect waited for a frame"
        go_on.set()
        frame = await camera.capture()
        assert frame.shape == (camera.model.height, camera.model.width, 3)
        assert drawn == [False, True], "the first frame, then the capture's own"
    finally:
        await camera.close()
