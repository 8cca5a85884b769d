"""A simulated cell commissioned once per test process, copied into each fresh data directory.

A fresh simulated cell commissions itself at start (server/bootstrap/commissioning.py:
a camera calibration, a robot calibration and the demo part in the library), which
renders and solves a dozen camera frames: the largest part of a rig's start-up. Most
tests only need a commissioned cell, not to watch one being commissioned, so
`seed_commissioned` writes what commissioning would have written into a fresh data
directory from a template: the same operations run once, on the same simulated
camera, by the same function the server calls, in a directory of their own.

A template is valid for every cell whose settings agree with it on each setting
commissioning read while it was made (recorded as it reads them), so a test that
changes the marker layout or the chessboard gets a template of its own, while one
that changes a port or a timeout shares the first. The cell still runs commissioning
at start: it finds the calibrations and the part on record, places the part on the
table and does nothing more, as on any later start.

The camera's noise generator is handed over too: commissioning drew from it once
per frame, so the rig's camera continues the sequence the fresh cell's would have.
"""

from __future__ import annotations

import atexit
import copy
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from server.bootstrap.commissioning import commission_simulated_cell
from server.core.worker.devices import CellDevices
from server.drivers.camera import SimulatedCamera
from server.drivers.sim.camera_scene import Scene
from server.settings.model import Settings
from server.storage import CellStores
from tests.fakes import FakeGlue, FakeRobot

# The simulated table is printed from these (server/bootstrap/devices.py), before
# commissioning reads any setting itself.
CAMERA_SETTINGS = ("marker_positions_mm", "marker_size_mm")
# The template camera's timeout: a bound on a frame, never a performance assertion; long,
# so a busy machine cannot fail a commissioning the cell itself would have completed.
CAMERA_TIMEOUT_S = 60.0


@dataclass(frozen=True)
class Template:
    """A data directory as commissioning left it, and what it depended on."""

    directory: Path
    read: dict[str, Any]  # each setting commissioning read, with its value
    noise: np.random.Generator  # the camera's noise generator after commissioning
    commissioned: bool  # every step succeeded (otherwise the cell commissions itself)

    def fits(self, settings: Settings) -> bool:
        return all(_same(getattr(settings, name), value) for name, value in self.read.items())


class _ReadingSettings:
    """The settings, noting each attribute read (fields and properties, not methods)."""

    def __init__(self, settings: Settings, read: dict[str, Any]) -> None:
        self._settings = settings
        self._read = read

    def __getattr__(self, name: str) -> Any:
        value = getattr(self._settings, name)
        if not callable(value):
            self._read[name] = copy.deepcopy(value)
        return value


_templates: list[Template] = []
_root: Path | None = None
# Where the templates go: the temporary directory when this was imported (at collection),
# not one a test points TMPDIR at while it runs (the benchmarks' smoke tests check that
# they leave nothing in theirs).
_TEMPORARY = tempfile.gettempdir()


def commissionable(settings: Settings, data_path: Path) -> bool:
    """A fresh data directory of a simulated cell that commissions itself at start."""
    fresh = not data_path.exists() or not any(data_path.iterdir())
    return fresh and settings.camera_simulated and settings.commission_simulated_cell


async def seed_commissioned(settings: Settings) -> Template | None:
    """Copy a commissioned template fitting `settings` into `settings.data_path` (fresh).

    None when commissioning fails with these settings: the cell then commissions itself
    at start and fails the same way, in its own log, as the test may expect."""
    template = next((t for t in _templates if t.fits(settings)), None)
    if template is None:
        template = await _commission(settings)
        _templates.append(template)
    if not template.commissioned:
        return None
    _copy_into(template.directory, settings.data_path)
    return template


def _copy_into(template: Path, data_path: Path) -> None:
    """The template's files into `data_path`; a directory that exists keeps its own mode
    (the cell tightens a loose one at start, and says so, as it would have)."""
    if not data_path.exists():
        shutil.copytree(template, data_path)  # private, as CellStores made the template
        return
    for entry in template.iterdir():
        if entry.is_dir():
            shutil.copytree(entry, data_path / entry.name)
        else:
            shutil.copy2(entry, data_path / entry.name)


def continue_noise(camera: SimulatedCamera, template: Template) -> None:
    """Give the rig's camera the noise generator the commissioning camera left off with."""
    camera._rng = copy.deepcopy(template.noise)  # the simulator's own, no public setter


async def _commission(settings: Settings) -> Template:
    """Commission a directory of its own, as Cell.start does on a fresh one."""
    global _root
    if _root is None:
        _root = Path(tempfile.mkdtemp(prefix="glue-commissioned-", dir=_TEMPORARY))
        atexit.register(shutil.rmtree, _root, True)
    directory = _root / f"cell-{len(_templates)}"
    read = {name: copy.deepcopy(getattr(settings, name)) for name in CAMERA_SETTINGS}
    scene = Scene.printed(settings.marker_positions_mm, settings.marker_size_mm)
    camera = SimulatedCamera(scene, timeout=CAMERA_TIMEOUT_S)
    # Commissioning never touches the robot or the glue: they only fill the context.
    devices = CellDevices(FakeRobot(), FakeGlue(), camera)
    stores = CellStores.open(directory)
    done = await commission_simulated_cell(
        devices,
        stores,
        _ReadingSettings(settings, read),  # type: ignore[arg-type]
    )
    await camera.close()
    commissioned = bool(done) and all(" commissioned: " in line for line in done)
    return Template(directory, read, copy.deepcopy(camera._rng), commissioned)


def _same(a: Any, b: Any) -> bool:
    try:
        return bool(a == b)
    except ValueError:  # arrays compare element-wise
        return bool(np.array_equal(a, b))
