"""One composition root: `create_app` builds the webhooks beside the plant links and the
latency machinery, and its lifespan starts and stops what it was given.

The webhooks are not the cell's: the root builds them from `WebhookSettings` and the
cell's bus, starts them once the cell is up and stops them between the cell's work and
its journal, so what they abandon is still journaled. The garbage collector's settings
are the server process's alone (`tune_process`): an app built in any other process
leaves its collector as it was.
"""

from __future__ import annotations

import gc
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest

from server.bootstrap.app import create_app
from server.bootstrap.cell import Cell
from server.bootstrap.latency import GC_THRESHOLDS
from server.core.worker.devices import CellDevices
from server.notify.notifier import Notifier
from server.settings.model import Settings
from tests.fakes import FakeCamera, FakeGlue, FakeRobot

# A webhook that hears only of shift reports: nothing in these tests makes one, so
# nothing is ever posted (no socket in the unit tier).
REPORTS_ONLY: dict[str, Any] = {
    "webhooks": [
        {
            "name": "mes",
            "url": "http://127.0.0.1:9/hook",
            "events": ["report"],
            "secret": "a-secret-of-the-plant-0123456789",
        }
    ],
    "webhook_allowed_networks": ["127.0.0.0/8"],
    # A camera by address: the fakes stand for the devices, no image process is started.
    "vision_camera_id": "0",
}


def cell_for(fast_settings: Settings) -> Cell:
    settings = Settings.model_validate({**fast_settings.model_dump(), **REPORTS_ONLY})
    return Cell(settings, devices=CellDevices(FakeRobot(), FakeGlue(), FakeCamera()))


def test_the_root_builds_the_webhooks_and_the_cell_does_not(fast_settings: Settings) -> None:
    cell = cell_for(fast_settings)
    app = create_app(cell=cell)
    webhooks = app.state.webhooks
    assert isinstance(webhooks, Notifier)
    assert webhooks.cell_id == cell.settings.cell_id
    assert [t.name for t in webhooks.settings.webhooks] == ["mes"]
    assert not hasattr(cell, "notifier")


async def test_the_lifespan_stops_the_webhooks_between_the_cells_work_and_its_journal(
    fast_settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    cell = cell_for(fast_settings)
    app = create_app(cell=cell)
    webhooks: Notifier = app.state.webhooks
    steps: list[str] = []

    def noted(name: str, step: Callable[[], Awaitable[None]]) -> Callable[[], Awaitable[None]]:
        async def run() -> None:
            steps.append(name)
            await step()

        return run

    monkeypatch.setattr(cell, "stop_running", noted("cell's work", cell.stop_running))
    monkeypatch.setattr(webhooks, "stop", noted("webhooks", webhooks.stop))
    monkeypatch.setattr(cell, "close_records", noted("cell's records", cell.close_records))
    async with app.router.lifespan_context(app):
        assert [d.name for d in webhooks.deliverers] == ["mes"], "started with the cell"
    assert steps == ["cell's work", "webhooks", "cell's records"]


def test_an_app_leaves_the_collector_as_it_was_unless_the_process_is_the_servers(
    tmp_path: Path,
) -> None:
    before = gc.get_threshold()
    try:
        gc.set_threshold(700, 10, 10)
        create_app(Settings(data_path=tmp_path / "a"))
        assert gc.get_threshold() == (700, 10, 10)
        create_app(Settings(data_path=tmp_path / "b"), tune_process=True)
        assert gc.get_threshold() == GC_THRESHOLDS
    finally:
        gc.unfreeze()
        gc.set_threshold(*before)
