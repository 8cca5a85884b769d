"""`glue-server` with no hardware configured: it starts its own simulators and
a bare POST /start drives a whole cycle (the README's first promise)."""

from __future__ import annotations

import time

import httpx

from tests.processes import server_process
from tests.serving import admin_headers, free_port


def test_default_server_runs_a_full_cycle_on_its_own_simulators(tmp_path) -> None:
    port = free_port()
    with server_process(port, tmp_path, {"GLUE_APP_SIMULATION_SPEED_FACTOR": "10"}):
        url = f"http://127.0.0.1:{port}"
        client = httpx.Client(base_url=url, headers=admin_headers(tmp_path), timeout=30)
        deadline = time.monotonic() + 30
        while client.get("/state").json()["state"] != "IDLE":
            assert time.monotonic() < deadline
            time.sleep(0.05)
        response = client.post("/start")
        assert response.status_code == 202, response.text
        while client.get("/state").json()["state"] != "IDLE":
            assert time.monotonic() < deadline + 30
            time.sleep(0.05)
        history = client.get("/history").json()["transitions"]
        assert [(t["old_state"], t["new_state"], t["event"]) for t in history[1::-1]] == [
            ("IDLE", "EXECUTING_TRAJECTORY", "START_REQUESTED"),
            ("EXECUTING_TRAJECTORY", "IDLE", "OPERATION_COMPLETED"),
        ]
        health = client.get("/health").json()
        assert health["status"] == "ok"
        assert "RTU over TCP" in health["devices"]["glue"]["link"]  # the production client
