"""GET /camera/frame over real sockets: the latest frame an operation measured on,
as a JPEG of the camera's size that says when it was taken and by which run, on
the commissioned simulated cell (robot and glue simulators behind their real
protocols, tests/rig.py)."""

from __future__ import annotations

import asyncio
import time

import cv2
import httpx
import numpy as np

from server.vision.outlines import outline_to_mm, part_outlines_px
from tests.rig import SPRAY_DEMO, Rig, open_rig, run


async def run_to_idle(rig: Rig, command: str, body: dict | None = None) -> dict:
    snapshot = await run(rig, command, body)
    assert snapshot["state"] == "IDLE", snapshot["error"]
    return snapshot


def decode(response: httpx.Response) -> np.ndarray:
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "image/jpeg"
    image = cv2.imdecode(np.frombuffer(response.content, np.uint8), cv2.IMREAD_COLOR)
    assert image is not None, "the body is not a decodable image"
    return image


async def last_run_id(rig: Rig, kind: str) -> str:
    response = await rig.api.get("/operations", params={"kind": kind, "limit": 1})
    return response.json()["operations"][0]["run_id"]


async def test_the_latest_frame_follows_the_operations_that_capture(tmp_path) -> None:
    async with open_rig(tmp_path) as rig:
        camera = rig.camera
        size = (camera.model.height, camera.model.width)

        # No token: 401 like every route but /health. A token, but nothing captured yet
        # (commissioning runs before the machine starts): 404 saying what captures one.
        async with httpx.AsyncClient(base_url=rig.api.base_url) as anonymous:
            refused = await anonymous.get("/camera/frame")
        assert refused.status_code == 401 and refused.headers["www-authenticate"] == "Bearer"
        missing = await rig.api.get("/camera/frame")
        assert missing.status_code == 404
        assert missing.headers["content-type"] == "application/json"
        assert "no camera frame captured" in missing.json()["detail"]
        assert "create a workpiece" in missing.json()["detail"]

        # A run with contour matching captures the table: that frame, with its run.
        before = time.time()
        await run_to_idle(rig, "start")
        trajectory = (await rig.api.get("/trajectory")).json()
        response = await rig.api.get("/camera/frame")
        image = decode(response)
        assert image.shape[:2] == size
        assert response.headers["x-frame-source"] == "trajectory"
        assert response.headers["x-frame-run-id"] == trajectory["run_id"]
        taken = float(response.headers["x-frame-time"])
        assert before <= taken <= time.time()
        assert response.headers["cache-control"] == "no-store"

        # It is the undistorted frame the run measured on: the part found in the served
        # JPEG, through the robot calibration, lies where the simulator put it.
        homography = rig.cell.stores.calibration.robot.homography
        outline = outline_to_mm((await asyncio.to_thread(part_outlines_px, image))[0], homography)
        placed = camera.scene.workpieces[0].centroid_table_mm()
        assert np.linalg.norm(outline.mean(axis=0) - placed) < 2.0

        # A run without contour matching and without inspection takes no picture: the frame
        # stays. (Inspected, a run photographs its part after the path: docs/quality.md.)
        patched = await rig.api.patch("/settings", json={"inspection_enabled": False})
        assert patched.status_code == 200, patched.text
        await run_to_idle(rig, "start", SPRAY_DEMO)
        same = await rig.api.get("/camera/frame")
        assert same.headers["x-frame-run-id"] == trajectory["run_id"]
        assert same.content == response.content  # encoded once, served again

        # Workpiece creation captures a new one, which replaces it.
        await run_to_idle(rig, "create-workpiece", {"name": "again", "workpiece_id": "again"})
        created = await rig.api.get("/camera/frame")
        assert decode(created).shape[:2] == size
        assert created.headers["x-frame-source"] == "create_workpiece"
        assert created.headers["x-frame-run-id"] == await last_run_id(rig, "create_workpiece")
        assert float(created.headers["x-frame-time"]) > taken

        # Any role that may look may see it.
        token = await rig.api.post("/tokens", json={"name": "hall", "role": "viewer"})
        viewer = {"Authorization": f"Bearer {token.json()['token']}"}
        assert (await rig.api.get("/camera/frame", headers=viewer)).status_code == 200
