"""The camera set-up view over real sockets (WebSocket /camera/preview/ws and
GET /camera/preview) on the commissioned simulated cell (tests/rig.py): who may watch,
how many at once, how fast, what each frame's figures say, and when it is refused."""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import cv2
import numpy as np
import pytest
import websockets
from websockets.asyncio.client import ClientConnection, connect

from tests.rig import WAIT_S, Rig, open_rig


async def token(rig: Rig, role: str) -> dict[str, str]:
    created = await rig.api.post("/tokens", json={"name": f"{role}-1", "role": role})
    assert created.status_code == 201, created.text
    return {"Authorization": f"Bearer {created.json()['token']}"}


def stream_url(rig: Rig) -> str:
    return str(rig.api.base_url).replace("http://", "ws://").rstrip("/") + "/camera/preview/ws"


@asynccontextmanager
async def watch(rig: Rig, headers: dict[str, str]) -> AsyncIterator[ClientConnection]:
    """Open the stream with a one-shot ticket, as the dashboard does."""
    ticket = (await rig.api.post("/ws-ticket", headers=headers)).json()["ticket"]
    async with connect(f"{stream_url(rig)}?ticket={ticket}", max_size=None) as ws:
        yield ws


async def next_frame(ws: ClientConnection) -> tuple[dict, np.ndarray]:
    """One frame's figures (text) and its picture (binary), in that order."""
    async with asyncio.timeout(WAIT_S):
        text = await ws.recv()
        picture = await ws.recv()
    assert isinstance(text, str) and isinstance(picture, bytes)
    image = cv2.imdecode(np.frombuffer(picture, np.uint8), cv2.IMREAD_COLOR)
    assert image is not None, "the binary message is not a JPEG"
    return json.loads(text), image


async def refused(rig: Rig, headers: dict[str, str] | None) -> tuple[int, str]:
    """The close code and reason of a refused stream (accepted, then closed at once)."""
    url = stream_url(rig)
    if headers is not None:
        ticket = (await rig.api.post("/ws-ticket", headers=headers)).json()["ticket"]
        url += f"?ticket={ticket}"
    async with connect(url) as ws:
        with pytest.raises(websockets.ConnectionClosed) as closed:
            async with asyncio.timeout(WAIT_S):
                await ws.recv()
    assert closed.value.rcvd is not None
    return closed.value.rcvd.code, closed.value.rcvd.reason


async def status(rig: Rig, headers: dict[str, str]) -> dict:
    response = await rig.api.get("/camera/preview", headers=headers)
    assert response.status_code == 200, response.text
    return response.json()


async def wait_status(rig: Rig, headers: dict[str, str], **expected: object) -> dict:
    async with asyncio.timeout(WAIT_S):
        while True:
            now = await status(rig, headers)
            if all(now[k] == v for k, v in expected.items()):
                return now
            await asyncio.sleep(0.05)


async def test_the_set_up_view_is_for_maintenance_and_shows_the_nine_markers(tmp_path) -> None:
    async with open_rig(tmp_path, camera_preview_fps=4) as rig:
        maintenance = await token(rig, "maintenance")
        operator = await token(rig, "operator")

        # Who: no ticket 4401, an operator's ticket 4403 naming the role; HTTP says 403.
        assert (await refused(rig, None))[0] == 4401
        code, detail = await refused(rig, operator)
        assert code == 4403 and "maintenance" in detail, detail
        forbidden = await rig.api.get("/camera/preview", headers=operator)
        assert forbidden.status_code == 403
        idle = await status(rig, maintenance)
        assert idle["allowed"] and not idle["running"] and idle["clients"] == 0

        async with watch(rig, maintenance) as ws:
            figures, image = await next_frame(ws)
            # The commissioned simulated table: nine markers, the workspace drawn through the
            # robot calibration, on the undistorted frame, scaled down for the stream.
            assert figures["markers_found"] == 9 and figures["markers_expected"] == 9
            assert figures["markers"] == list(range(9)) and figures["missing"] == []
            assert figures["workspace_drawn"] and figures["workspace_note"] is None
            assert figures["undistorted"]
            assert figures["camera_size"] == [1920, 1080]
            assert [image.shape[1], image.shape[0]] == figures["image_size"]
            assert 0 < figures["brightness"] < 255 and figures["sharpness"] > 0
            now = await status(rig, maintenance)
            assert now["running"] and now["clients"] == 1
            assert now["last_frame"]["markers_found"] == 9

            # Degrade the camera: a lens out of focus, then the light turned down.
            rig.camera.scene.defocus_px = 4.0
            await next_frame(ws)  # may have been captured before the change
            blurred, _ = await next_frame(ws)
            assert blurred["sharpness"] < figures["sharpness"] / 2, (blurred, figures)
            rig.camera.scene.defocus_px = 0.0
            rig.camera.scene.exposure = 0.4
            await next_frame(ws)
            dark, _ = await next_frame(ws)
            assert dark["brightness"] < figures["brightness"] * 0.6, (dark, figures)

        # Nobody watches: no capture goes on.
        await wait_status(rig, maintenance, running=False, clients=0)


async def test_clients_and_rate_are_bounded(tmp_path) -> None:
    fps = 2.0
    async with open_rig(tmp_path, camera_preview_fps=fps, camera_preview_clients=2) as rig:
        maintenance = await token(rig, "maintenance")
        async with watch(rig, maintenance) as first, watch(rig, maintenance) as second:
            code, detail = await refused(rig, maintenance)
            assert code == 1013 and "camera_preview_clients" in detail, detail

            # Frames counted over a window the client measures: at most fps a second (one
            # producer for both clients), with a margin of two frames for the window's ends.
            seqs = [(await next_frame(first))[0]["seq"]]
            window = 4.0
            started = time.monotonic()
            while time.monotonic() - started < window:
                seqs.append((await next_frame(first))[0]["seq"])
            elapsed = time.monotonic() - started
            assert len(seqs) <= fps * elapsed + 2, (len(seqs), elapsed)
            assert seqs == sorted(set(seqs))
            # One producer for both: the second client's frames are numbered in the same run.
            latest, _ = await next_frame(second)
            assert 1 <= latest["seq"] <= seqs[-1] + 1

        # Both gone: a slot is free again.
        await wait_status(rig, maintenance, clients=0)
        async with watch(rig, maintenance) as again:
            await next_frame(again)


async def test_refused_outside_idle_and_ended_when_the_cell_leaves_it(tmp_path) -> None:
    async with open_rig(tmp_path) as rig:
        maintenance = await token(rig, "maintenance")
        async with watch(rig, maintenance) as ws:
            await next_frame(ws)
            await rig.start_spraying()
            with pytest.raises(websockets.ConnectionClosed) as closed:
                async with asyncio.timeout(WAIT_S):
                    while True:
                        await ws.recv()
            assert closed.value.rcvd is not None and closed.value.rcvd.code == 4409
            assert "EXECUTING_TRAJECTORY" in closed.value.rcvd.reason
        # Paused, the run still holds the camera: refused up front, naming the state.
        assert (await rig.api.post("/pause")).status_code == 202
        await rig.wait_state("PAUSED")
        code, detail = await refused(rig, maintenance)
        assert code == 4409 and "PAUSED" in detail and "IDLE" in detail, detail
        now = await status(rig, maintenance)
        assert not now["allowed"] and "PAUSED" in now["reason"]
        assert (await rig.api.post("/cancel")).status_code == 202
        await rig.wait_state("IDLE")
        async with watch(rig, maintenance) as ws:
            await next_frame(ws)
