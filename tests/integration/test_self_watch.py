"""The cell watches itself, on the served cell with its simulators: its memory against
memory_limit, the data directory's free space, a configuration change, and the figures
in GET /health and GET /metrics. Each warning is checked where people see it: the
WebSocket `alert` and the journal's errors (classification warning)."""

from __future__ import annotations

import asyncio
import json
import os
from collections.abc import AsyncIterator
from typing import Any

import pytest
from websockets.asyncio.client import ClientConnection, connect

from server.core.worker.runs import RunEnded
from server.watch.system import process_use
from tests.rig import Rig, open_rig

FAST_WATCH = {"watch_interval_s": 0.05}


@pytest.fixture
async def rig(tmp_path) -> AsyncIterator[Rig]:
    async with open_rig(tmp_path, **FAST_WATCH) as running:
        yield running


def alerts_socket(rig: Rig) -> connect:
    url = str(rig.api.base_url).replace("http", "ws", 1) + "/ws?types=alert"
    return connect(url, additional_headers={"Authorization": rig.api.headers["authorization"]})


async def alert_on(ws: ClientConnection, code: str) -> dict[str, Any]:
    """The next `alert` with `code` on the socket (its data)."""
    async with asyncio.timeout(30):
        while True:
            message = json.loads(await ws.recv())
            if message.get("type") != "alert":
                continue
            data = message.get("data", message)
            if data.get("code") == code:
                return data


async def warning_rows(rig: Rig, code: str) -> list[dict[str, Any]]:
    """The journal's warnings with `code` (GET /errors), once written."""
    async with asyncio.timeout(30):
        while True:
            response = await rig.api.get("/errors", params={"code": code})
            rows = response.json()["errors"]
            if rows:
                return rows
            await asyncio.sleep(0.05)


async def test_a_memory_limit_below_what_the_cell_uses_raises_the_alert(rig: Rig) -> None:
    async with alerts_socket(rig) as ws:
        await ws.recv()  # the snapshot
        rig.cell.settings.memory_limit = "1MB"
        alert = await alert_on(ws, "MEMORY_LIMIT_REACHED")
    assert alert["severity"] == "alert" and alert["component"] == "system"
    assert "memory_limit 1MB" in alert["message"]
    row = (await warning_rows(rig, "MEMORY_LIMIT_REACHED"))[0]
    assert row["classification"] == "warning"
    health = (await rig.api.get("/health")).json()
    assert health["system"]["memory"]["level"] == "alert"
    assert (await rig.state())["state"] == "IDLE"  # never a crash, nothing stopped


async def test_memory_at_the_warning_share_of_the_limit_raises_the_warning(rig: Rig) -> None:
    resident = process_use(os.getpid()).resident_bytes  # the server runs in this process
    assert resident is not None
    # A limit twice what the server uses now, warned of at 10 % of it: a warning, no alert.
    limit_mb = 2 * resident // 1024**2
    async with alerts_socket(rig) as ws:
        await ws.recv()
        rig.cell.settings.memory_warning_percent = 10.0
        rig.cell.settings.memory_limit = f"{limit_mb}MB"
        alert = await alert_on(ws, "MEMORY_HIGH")
    assert alert["severity"] == "warning"
    assert f"memory_limit {limit_mb}MB" in alert["message"]
    assert (await rig.api.get("/health")).json()["system"]["memory"]["level"] == "warning"


async def test_free_space_under_the_threshold_raises_the_warning(rig: Rig) -> None:
    async with alerts_socket(rig) as ws:
        await ws.recv()
        rig.cell.settings.free_space_warning = "1000000GB"  # more than any real disk has free
        alert = await alert_on(ws, "DISK_SPACE_LOW")
    assert alert["component"] == "storage" and "free_space_warning" in alert["message"]
    disk = (await rig.api.get("/health")).json()["system"]["disk"]
    assert disk["free_bytes"] < disk["warning_bytes"]
    assert (await warning_rows(rig, "DISK_SPACE_LOW"))[0]["classification"] == "warning"


async def test_a_configuration_change_raises_an_alert_naming_who_and_what(rig: Rig) -> None:
    async with alerts_socket(rig) as ws:
        await ws.recv()
        response = await rig.api.patch("/settings", json={"design_cycle_time_s": 42})
        assert response.status_code == 200
        alert = await alert_on(ws, "CONFIGURATION_CHANGED")
    assert alert["severity"] == "alert" and alert["component"] == "settings"
    who = "initial admin (admin)"  # the admin token the server made on first start
    assert alert["message"] == f"{who} changed design_cycle_time_s from 30.0 to 42.0"
    assert "Bearer" not in alert["message"]


async def test_health_and_metrics_show_the_cells_own_figures(tmp_path) -> None:
    # The specification's limit, which the rig leaves unwatched (tests/rig.py)
    async with open_rig(tmp_path, **FAST_WATCH, memory_limit="512MB") as rig:
        await _figures_shown(rig)


async def _figures_shown(rig: Rig) -> None:
    system = (await rig.api.get("/health")).json()["system"]
    assert system["server"]["resident_bytes"] > system["server"]["unique_bytes"] > 0
    assert system["server"]["threads"] >= 1 and system["server"]["open_files"] >= 3
    assert system["memory"]["limit_bytes"] == 512 * 1024**2  # the specification's default
    assert system["disk"]["free_bytes"] > 0 and system["loop_lag_ms"] >= 0
    assert system["image_process"] is not None  # started with the cell
    assert system["image_process"]["unique_bytes"] > 0
    async with asyncio.timeout(30):  # the links' round trips, once looked at
        while not (await rig.api.get("/health")).json()["system"]["links"]:
            await asyncio.sleep(0.05)
    metrics = (await rig.api.get("/metrics")).text
    for series in (
        'glue_cell_memory_bytes{kind="unique",process="server"}',
        'glue_cell_memory_bytes{kind="resident",process="image"}',
        'glue_cell_threads{process="server"}',
        'glue_cell_open_files{process="server"}',
        "glue_cell_memory_limit_bytes 5.36870912e+08",
        "glue_cell_event_loop_lag_seconds",
        "glue_cell_data_free_bytes",
        'glue_cell_device_rtt_p95_seconds{device="robot"}',
    ):
        assert series in metrics, series


async def test_a_rising_error_rate_raises_an_alert(tmp_path) -> None:
    """Runs' ends told to the run listeners as the worker tells them: with a window of 4
    and at most 40 per 100, the second failure among the latest four is the alert."""
    settings = {**FAST_WATCH, "error_rate_window_operations": 4, "error_rate_alert_per_100": 40}
    async with open_rig(tmp_path, **settings) as rig, alerts_socket(rig) as ws:
        await ws.recv()
        listeners = rig.cell.worker.runs.listeners  # type: ignore[union-attr]
        for index, outcome in enumerate(("completed", "failed", "completed", "completed")):
            ended = RunEnded(f"r{index}", "trajectory", outcome, 1.0, "SPRAYING", None, None, 1)
            for listener in listeners:
                listener(ended)
        await asyncio.sleep(0.1)
        assert (await rig.api.get("/health")).json()["system"]["error_rate"] == {
            "per_100": 25.0, "operations": 4, "window": 4,
        }  # fmt: skip
        failed = RunEnded("r4", "trajectory", "failed", 1.0, "SPRAYING", None, "jam", 1)
        for listener in listeners:
            listener(failed)
        alert = await alert_on(ws, "ERROR_RATE_RISING")
    assert alert["severity"] == "alert"
    assert alert["message"].startswith("2 of the last 4 operations failed, 50 per 100")


async def test_a_robot_link_answering_late_raises_the_degrading_warning(tmp_path) -> None:
    """The robot simulator answers 150 ms late after a baseline of quick answers: its p95
    round trip over the latest window passes 3 times the baseline's and 20 ms over it."""
    settings = {**FAST_WATCH, "robot_heartbeat_interval": 0.05, "rtt_window_samples": 5}
    async with open_rig(tmp_path, **settings) as rig, alerts_socket(rig) as ws:
        await ws.recv()
        async with asyncio.timeout(30):  # the baseline: the first full window
            while rig.cell.watch is None or rig.cell.watch.links["robot"].baseline is None:
                await asyncio.sleep(0.05)
        rig.robot.delay_answers(150)
        alert = await alert_on(ws, "LINK_DEGRADING")
        link = (await rig.api.get("/health")).json()["system"]["links"]["robot"]
        rig.robot.clear_faults()
    assert alert["component"] == "robot" and alert["severity"] == "warning"
    assert alert["message"].startswith("the robot's round trips are degrading: p95 ")
    assert link["samples"] == 5 and link["baseline_p95_ms"] < link["p95_ms"]
