"""The bead the simulated cell dispenses, seen by its camera, and the faults that spoil it,
acting through the real simulators (Modbus, JSON-RPC, the glue's control channel)."""

from __future__ import annotations

import asyncio
import json

import numpy as np
import pytest

from server.bootstrap.devices import build_devices
from server.drivers.camera import SimulatedCamera
from server.drivers.glue_modbus import ModbusGlueDispenser
from server.drivers.sim.camera_bead import dispensed_by
from server.drivers.sim.glue_sim import GlueSimulator
from server.settings.model import Settings
from server.vision.bead import expected_bead_width_mm
from tests.rig import SPRAY_DEMO, Rig, open_rig, run


def glue_seen(camera: SimulatedCamera, frame: np.ndarray, points_mm: np.ndarray) -> np.ndarray:
    """Red minus blue in the raw frame where the table points appear (the glue is amber)."""
    pixels = np.rint(camera.model.table_to_pixel(points_mm)).astype(int)
    bgr = frame[pixels[:, 1], pixels[:, 0]].astype(float)
    return bgr[:, 2] - bgr[:, 0]


def sprayed_points(rig: Rig) -> tuple[np.ndarray, np.ndarray]:
    """Points along the moves made with the valve open, and along those made with it closed
    (from the simulators' own records), 1 mm apart, ends left out."""
    changes = list(rig.glue.valve_log)

    def open_at(t: float) -> bool:
        state = False
        for at, is_open in changes:
            if at <= t:
                state = is_open
        return state

    sprayed, dry = [], []
    for segment in rig.robot.executed_path:
        start, end = np.array(segment.start[:2]), np.array(segment.end[:2])
        length = float(np.hypot(*(end - start)))
        if length < 10:
            continue
        inner = np.linspace(3.0 / length, 1 - 3.0 / length, int(length))
        points = start + inner[:, None] * (end - start)
        middle = (segment.t_start + segment.t_end) / 2
        (sprayed if open_at(middle) else dry).append(points)
    return np.vstack(sprayed), np.vstack(dry) if dry else np.zeros((0, 2))


async def test_a_run_leaves_a_bead_where_the_valve_was_open(tmp_path) -> None:
    async with open_rig(tmp_path) as rig:
        rig.camera.bead_source = dispensed_by(rig.robot, rig.glue)
        before = await rig.camera.capture()
        snapshot = await run(rig, "start", SPRAY_DEMO)
        assert snapshot["state"] == "IDLE", snapshot
        after = await rig.camera.capture()
        sprayed, dry = sprayed_points(rig)
        assert len(sprayed) > 200
        # glue along every sprayed move, none there before the run
        assert np.median(glue_seen(rig.camera, after, sprayed)) > 80
        assert np.median(glue_seen(rig.camera, before, sprayed)) < 20
        # nothing along the travel moves (valve closed) away from the bead
        far = [p for p in dry if np.min(np.hypot(*(sprayed - p).T)) > 6]
        if far:
            assert np.median(glue_seen(rig.camera, after, np.array(far))) < 20
        # the part taken off the table takes its bead with it
        rig.camera.clear_workpieces()
        cleared = await rig.camera.capture()
        assert np.median(glue_seen(rig.camera, cleared, sprayed)) < 20


async def _a_sprayed_part_seen(rig: Rig) -> np.ndarray:
    """One run of the demo part, its bead seen by the camera: the points sprayed."""
    rig.camera.bead_source = dispensed_by(rig.robot, rig.glue)
    snapshot = await run(rig, "start", SPRAY_DEMO)
    assert snapshot["state"] == "IDLE", snapshot
    sprayed, _ = sprayed_points(rig)
    assert np.median(glue_seen(rig.camera, await rig.camera.capture(), sprayed)) > 80
    return sprayed


async def test_the_next_part_of_an_order_comes_without_the_glue_of_the_last(tmp_path) -> None:
    async with open_rig(tmp_path) as rig:
        sprayed = await _a_sprayed_part_seen(rig)
        rig.camera.present_next_part()  # what an order does between its parts
        fresh = await rig.camera.capture()
        assert np.median(glue_seen(rig.camera, fresh, sprayed)) < 20


async def test_the_next_start_after_a_completed_run_sprays_a_fresh_part(tmp_path) -> None:
    """Outside an order too, a finished part leaves the table as the next run starts, so the
    bead the camera draws does not grow with every run ever made."""
    async with open_rig(tmp_path) as rig:
        sprayed = await _a_sprayed_part_seen(rig)
        # the next run is cancelled as it starts, long before it sprays
        assert (await rig.api.post("/start", json=SPRAY_DEMO)).status_code == 202
        assert (await rig.api.post("/cancel")).status_code == 202
        assert (await rig.wait_state("IDLE"))["state"] == "IDLE"
        fresh = await rig.camera.capture()
        assert np.median(glue_seen(rig.camera, fresh, sprayed)) < 20


async def test_a_part_shifted_while_spraying_carries_the_glue_already_on_it(tmp_path) -> None:
    async with open_rig(tmp_path) as rig:
        rig.camera.bead_source = dispensed_by(rig.robot, rig.glue)
        await rig.start_spraying()
        await asyncio.sleep(0.3)
        rig.camera.shift_part(0.0, 6.0)
        snapshot = await rig.wait_state("IDLE")
        assert snapshot["state"] == "IDLE"
        frame = await rig.camera.capture()
        sprayed, _ = sprayed_points(rig)
        on_plan = glue_seen(rig.camera, frame, sprayed)
        moved = glue_seen(rig.camera, frame, sprayed + np.array([0.0, 6.0]))
        # some of the bead went with the part, the rest landed on the plan
        assert (moved > 80).sum() > 20 and (on_plan > 80).sum() > 20


async def test_a_knocked_camera_shows_the_table_displaced(tmp_path) -> None:
    camera = SimulatedCamera()
    await camera.connect()
    try:
        markers = np.asarray(camera.scene.marker_positions_mm)
        before = camera.model.table_to_pixel(markers)
        camera.knock(2.0, 0.0)
        after = camera.model.table_to_pixel(markers)
        frame = await camera.capture()
        assert frame.shape == (camera.model.height, camera.model.width, 3)
        # ~0.65 mm a pixel: 2 mm is about 3 px, the same for every marker
        moved = np.hypot(*(after - before).T)
        assert np.all(moved > 2.0) and np.ptp(moved) < 0.5
        camera.knock(0.0, 0.0)
        assert np.allclose(camera.model.table_to_pixel(markers), before)
    finally:
        await camera.close()


async def control(port: int, request: dict) -> dict:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        writer.write(json.dumps(request).encode() + b"\n")
        await writer.drain()
        return json.loads(await reader.readline())
    finally:
        writer.close()


async def test_glue_faults_through_the_control_channel() -> None:
    async with GlueSimulator(control_port=0, noise=False, speed_factor=4) as sim:
        glue = ModbusGlueDispenser.tcp("127.0.0.1", sim.port, device_id=sim.device_id, timeout=2)
        await glue.connect()
        try:
            assert sim.control_port is not None
            await glue.set_flow_rate(30.0)
            # a partly clogged nozzle: the flow reading shows the drop
            assert (await control(sim.control_port, {"cmd": "clog", "fraction": 0.4}))["ok"]
            await glue.set_valve(True)
            await asyncio.sleep(0.3)
            assert (await glue.read_status()).flow_ml_min == pytest.approx(12.0, abs=0.5)
            await glue.set_valve(False)
            # a valve that opens late: still closed right after the command, open later
            reply = await control(sim.control_port, {"cmd": "late_valve", "ms": 2000})
            assert reply["status"]["valve_delay_ms"] == 2000
            await glue.set_valve(True)  # 2 s of simulated time, 0.5 s at speed factor 4
            assert not (await glue.read_status()).valve_open
            await asyncio.sleep(0.7)
            assert (await glue.read_status()).valve_open
            opened = [t for t, is_open, _ in sim.history if is_open]
            closed = [t for t, is_open in sim.valve_log if not is_open]
            assert opened[-1] - closed[-1] == pytest.approx(0.5, abs=0.1)
            await glue.set_valve(False)
            assert (await control(sim.control_port, {"cmd": "clear"}))["status"][
                "clog_fraction"
            ] == 1.0
            bad = await control(sim.control_port, {"cmd": "clog", "fraction": 2})
            assert not bad["ok"] and "between 0 and 1" in bad["error"]
        finally:
            await glue.close()


async def test_the_simulated_camera_shows_the_bead_only_with_the_simulators_in_process(
    tmp_path,
) -> None:
    devices, release = await build_devices(Settings(data_path=tmp_path))
    try:
        assert isinstance(devices.camera, SimulatedCamera)
        assert devices.camera.bead_source is not None
    finally:
        await release()
    settings = Settings(data_path=tmp_path, robot_ip="127.0.0.1", robot_port=1)
    devices, release = await build_devices(settings)
    try:
        assert isinstance(devices.camera, SimulatedCamera)
        assert devices.camera.bead_source is None
    finally:
        await release()
    assert expected_bead_width_mm(30.0, 100.0) > 0
