"""openapi.json as a generator takes it: openapi-python-client (the test extra) makes a
client package from the repository's openapi.json, with the repository's generator
configuration, with no warning and no error; the
package imports, and it drives a served cell through calibrate → start → pause →
resume → estop → reset, the state checked after each through the client's own
getState. The start body is the generated typed model (`StartRequest`), not a dict.

Generating needs nothing from the network: the generator and its ruff are installed
by `make test` with the test extra.
"""

from __future__ import annotations

import asyncio
import importlib
import os
import subprocess
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

from tests.rig import WAIT_S, Rig, open_rig
from tests.serving import admin_headers

ROOT = Path(__file__).resolve().parents[2]
OPENAPI = ROOT / "openapi.json"
# What openapi-python-client is told (clients/openapi-python-client.yaml): read the image
# media types as the binary bodies they are described as.
CONFIG = ROOT / "clients" / "openapi-python-client.yaml"
PACKAGE = "glue_cell_client"


def generate(into: Path) -> str:
    """Run openapi-python-client on openapi.json; its output (it must have succeeded)."""
    bin_dir = Path(sys.executable).parent  # the generator and the ruff it formats with
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}"}
    generated = subprocess.run(
        [
            str(bin_dir / "openapi-python-client"),
            "generate",
            "--path",
            str(OPENAPI),
            "--output-path",
            str(into / PACKAGE),
            "--meta",
            "none",
            "--config",
            str(CONFIG),
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=WAIT_S * 3,
    )
    output = generated.stdout + generated.stderr
    assert generated.returncode == 0, output
    return output


@pytest.fixture(scope="module")
def client_package(tmp_path_factory: pytest.TempPathFactory) -> ModuleType:
    """The generated package, imported from its own directory."""
    root = tmp_path_factory.mktemp("generated")
    output = generate(root)
    assert "WARNING" not in output and "rror" not in output, output
    sys.path.insert(0, str(root))
    try:
        package = importlib.import_module(PACKAGE)
        for module in ("api.commands.start", "api.queries.get_state", "models"):
            importlib.import_module(f"{PACKAGE}.{module}")
    finally:
        sys.path.remove(str(root))
    return package


def test_the_generated_client_imports_and_types_the_start_body(client_package) -> None:
    models = importlib.import_module(f"{PACKAGE}.models")
    body = models.StartRequest(contour_matching=False, workpiece_id="demo")
    assert body.to_dict() == {"contour_matching": False, "workpiece_id": "demo"}
    assert models.StartRequest.from_dict({"contour_matching": False}).contour_matching is False
    # The image routes answer a binary body the client returns as a File.
    frame = importlib.import_module(f"{PACKAGE}.api.queries.get_camera_frame")
    assert "File" in str(frame.sync.__annotations__["return"])


async def test_the_generated_client_drives_a_cycle(client_package, tmp_path: Path) -> None:
    commands = {
        name: importlib.import_module(f"{PACKAGE}.api.commands.{name}")
        for name in ("calibrate_robot", "start", "pause", "resume", "estop", "reset")
    }
    get_state = importlib.import_module(f"{PACKAGE}.api.queries.get_state")
    models = importlib.import_module(f"{PACKAGE}.models")
    async with open_rig(tmp_path / "data", robot_speed_factor=1) as rig:
        token = admin_headers(tmp_path / "data")["Authorization"].removeprefix("Bearer ")
        client = client_package.AuthenticatedClient(
            base_url=str(rig.api.base_url).rstrip("/"), token=token, timeout=None
        )
        async with client:

            async def command(name: str, decided: str, **body: Any) -> None:
                """Send a command through the client: accepted, in state `decided`."""
                answer = await commands[name].asyncio_detailed(client=client, **body)
                assert answer.status_code == 202, (name, answer.content)
                assert (answer.parsed.accepted, answer.parsed.state) == (True, decided)

            async def state_is(expected: str) -> None:
                async with asyncio.timeout(WAIT_S):
                    while (await get_state.asyncio(client=client)).state != expected:
                        await asyncio.sleep(0.01)

            await command("calibrate_robot", "CALIBRATING_ROBOT")
            await state_is("IDLE")
            start = models.StartRequest(contour_matching=False, workpiece_id="demo")
            await command("start", "EXECUTING_TRAJECTORY", body=start)
            await until_spraying(rig)
            await command("pause", "PAUSED")
            await state_is("PAUSED")
            await command("resume", "EXECUTING_TRAJECTORY")
            await state_is("EXECUTING_TRAJECTORY")
            reason = models.EstopRequest(reason="generated client")
            await command("estop", "ERROR", body=reason)
            await state_is("ERROR")
            await command("reset", "IDLE")
            await state_is("IDLE")


async def until_spraying(rig: Rig) -> None:
    """The run has reached its spray path (the valve is open): a pause lands mid-run."""
    async with asyncio.timeout(WAIT_S):
        while not rig.glue.valve_open:
            await asyncio.sleep(0.005)
