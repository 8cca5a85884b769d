"""A network camera simulator: the simulated table as an MJPEG stream over HTTP.

Serves what an IP camera serves, so the cell's `OpenCVCamera` reads it through
OpenCV's own video I/O, exactly as it reads a real one
(`GLUE_APP_VISION_CAMERA_ID=http://HOST:PORT/stream.mjpg`):

- `GET /stream.mjpg`: `multipart/x-mixed-replace` JPEG frames at `--fps`;
- `GET /frame.jpg`: one JPEG frame.

It shows the table of the simulated cell (its printed markers, the demo part
where commissioning puts it), drawn by the same renderer as the in-process
simulated camera with the same camera model, so a data directory commissioned
on the simulated camera fits it. The table is still: a few frames (each with
its own sensor noise) are drawn at start and served in turn. It has no record
of the glue the robot laid, so an inspection finds no bead on the part.

Why it exists: to run the cell with every device out of its process (the robot
and dispenser simulators on their ports, this camera on its own) as a plant
runs it, for `bench.memory --cell` (the `devices` layout) and for an integrator
trying a network camera's settings.

Run: `python -m server.drivers.sim.camera_stream --port 8081`; it prints
"camera stream listening on HOST:PORT" once listening.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import itertools
import logging
from collections.abc import Sequence

import cv2
import numpy as np

from server.drivers.sim.camera_model import DEFAULT_CAMERA_MODEL
from server.drivers.sim.camera_scene import Scene, clear_render_caches, render_table
from server.drivers.sim.camera_workpieces import DEMO_WORKPIECE
from server.drivers.sim.standalone import (
    run_standalone,
    serve_until_signalled,
    simulator_arguments,
)
from server.settings.calibration import CalibrationSettings

logger = logging.getLogger(__name__)

BOUNDARY = b"frame"
JPEG_QUALITY = 90
NOISE_VARIANTS = 4  # frames drawn at start, each with its own sensor noise
REQUEST_LIMIT = 8192  # bytes of request line and headers read before giving up


def table_frames(count: int = NOISE_VARIANTS, seed: int = 0) -> list[bytes]:
    """`count` JPEG frames of the simulated cell's table with the demo part on it."""
    settings = CalibrationSettings()
    scene = Scene.printed(settings.marker_positions_mm, settings.marker_size_mm)
    scene.place_workpiece(*DEMO_WORKPIECE)
    rng = np.random.default_rng(seed)
    frames = []
    for _ in range(count):
        image = render_table(scene, DEFAULT_CAMERA_MODEL, rng)
        ok, encoded = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:
            raise RuntimeError("the simulated table could not be encoded as JPEG")
        frames.append(encoded.tobytes())
    clear_render_caches()  # the table is drawn: its maps are not needed again
    return frames


class CameraStream:
    """The HTTP server: one stream per connection, each at `fps`."""

    def __init__(self, frames: Sequence[bytes], fps: float, host: str, port: int) -> None:
        if fps <= 0:
            raise ValueError("fps must be greater than 0")
        self.frames = list(frames)
        self.period = 1.0 / fps
        self.host, self.port = host, port
        self._server: asyncio.Server | None = None

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._serve, self.host, self.port)
        self.port = self._server.sockets[0].getsockname()[1]

    async def stop(self) -> None:
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            head = await reader.readuntil(b"\r\n\r\n")
            path = _path_of(head)
            if path == "/stream.mjpg":
                await self._stream(writer)
            elif path == "/frame.jpg":
                writer.write(_response(b"image/jpeg", self.frames[0]))
                await writer.drain()
            else:
                writer.write(_response(b"text/plain", b"not found", status=b"404 Not Found"))
                await writer.drain()
        except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, ConnectionError):
            pass  # the client went away, or sent no request: nothing to answer
        except asyncio.CancelledError:
            pass  # the simulator is stopping: the stream ends with it
        finally:
            writer.close()
            with contextlib.suppress(ConnectionError):
                await writer.wait_closed()

    async def _stream(self, writer: asyncio.StreamWriter) -> None:
        writer.write(
            b"HTTP/1.0 200 OK\r\nCache-Control: no-cache\r\n"
            b"Content-Type: multipart/x-mixed-replace; boundary=" + BOUNDARY + b"\r\n\r\n"
        )
        for frame in itertools.cycle(self.frames):
            writer.write(
                b"--" + BOUNDARY + b"\r\nContent-Type: image/jpeg\r\n"
                b"Content-Length: " + str(len(frame)).encode() + b"\r\n\r\n" + frame + b"\r\n"
            )
            await writer.drain()  # a reader that does not keep up holds the stream back
            await asyncio.sleep(self.period)


def _path_of(head: bytes) -> str:
    """The path of a request's first line (`GET /path HTTP/1.1`); "" if it is not a GET."""
    parts = head.split(b"\r\n", 1)[0].split()
    if len(parts) < 2 or parts[0] != b"GET":
        return ""
    return parts[1].split(b"?", 1)[0].decode("ascii", "replace")


def _response(kind: bytes, body: bytes, status: bytes = b"200 OK") -> bytes:
    return (
        b"HTTP/1.0 " + status + b"\r\nContent-Type: " + kind + b"\r\n"
        b"Content-Length: " + str(len(body)).encode() + b"\r\n\r\n" + body
    )


async def _run(args: argparse.Namespace) -> None:
    frames = await asyncio.to_thread(table_frames)
    stream = CameraStream(frames, args.fps, args.host, args.port)
    await stream.start()
    await serve_until_signalled(stream, "camera stream")


def main(argv: Sequence[str] | None = None) -> None:
    """Command-line entry: serve until SIGTERM or SIGINT."""
    parser = simulator_arguments("Network camera simulator (MJPEG over HTTP)", 8081)
    parser.add_argument("--fps", type=float, default=10.0, help="frames a second per stream")
    run_standalone(_run, parser, argv)


if __name__ == "__main__":
    main()
