"""GET /metrics as Prometheus's own tools take it: a real scrape of a cell with every plant
link up (Debian's mosquitto, an OPC UA client's session, a webhook) piped through
promtool's `check metrics`, which must find nothing; base units and 0-1 ratios beside
the deprecated mm and percent series; no `_created` series; the standard process and
Python collectors; the build; and a series for each plant link, the webhook's by its
name only (its URL is its receiver's secret)."""

from __future__ import annotations

import asyncio
import platform
import re
import shutil
import subprocess
from pathlib import Path

import pytest
from asyncua import Client

from server.common.build import package_version
from tests.integration.test_part_verdicts import metric, summary, tell_run_ended
from tests.mosquitto import mosquitto
from tests.rig import WAIT_S, Rig, open_rig
from tests.serving import free_port

PROMTOOL = shutil.which("promtool")
# A webhook to a loopback port nobody listens on (a free one), allowed by the
# destination policy and tried once: each notice fails at once, a delivery failure.
SECRET_PATH = "/hooks/glue?token=never-in-metrics"


def promtool_findings(text: str) -> str:
    """What `promtool check metrics` says of an exposition (empty: clean)."""
    assert PROMTOOL is not None, (
        "promtool is missing: install Debian's prometheus package (make test does)"
    )
    checked = subprocess.run(
        [PROMTOOL, "check", "metrics"], input=text.encode(), capture_output=True, timeout=WAIT_S
    )
    findings = (checked.stdout + checked.stderr).decode().strip()
    assert checked.returncode == 0 or findings, checked.returncode
    return findings


async def scrape(rig: Rig) -> str:
    answer = await rig.api.get("/metrics")
    assert answer.status_code == 200, answer.text
    return answer.text


async def until_metric(rig: Rig, series: str, value: float) -> str:
    """Scrape until `series` has `value`; the last scrape."""
    async with asyncio.timeout(WAIT_S):
        while True:
            text = await scrape(rig)
            if re.search(rf"^{re.escape(series)} {re.escape(str(value))}$", text, re.M):
                return text
            await asyncio.sleep(0.05)


async def test_a_scrape_is_promtool_clean_in_base_units_with_every_plant_link(
    tmp_path: Path,
) -> None:
    opcua_port = free_port()
    webhook_address = f"127.0.0.1:{free_port()}"
    webhook = {
        "name": "mes",
        "url": f"http://{webhook_address}{SECRET_PATH}",
        "events": ["state"],
        "secret": "s" * 32,
    }
    with mosquitto(tmp_path / "broker") as broker:
        settings = {
            **broker.cell_login,
            "opcua_endpoint": f"opc.tcp://127.0.0.1:{opcua_port}",
            "webhooks": [webhook],
            "webhook_allowed_networks": ["127.0.0.0/8"],
            "webhook_max_attempts": 1,
        }
        async with open_rig(tmp_path / "data", **settings) as rig:
            # One inspected part: 2.5 mm and 3 % are exposed as metres and a ratio too.
            tell_run_ended(rig, "run-1", summary("good", [], 2.5))
            await until_metric(rig, "glue_cell_mqtt_connected", 1.0)
            async with Client(f"opc.tcp://127.0.0.1:{opcua_port}", timeout=WAIT_S):
                text = await until_metric(rig, "glue_cell_opcua_sessions", 1.0)
            text = await until_metric(
                rig, 'glue_cell_webhook_deliveries_total{outcome="failed",webhook="mes"}', 1.0
            )

            assert promtool_findings(text) == ""
            assert not [line for line in text.splitlines() if "_created" in line]

            # Base units and ratios; the old series stay one release, marked deprecated.
            assert metric(text, "glue_cell_part_trajectory_precision_meters_sum") == (
                pytest.approx(0.0025)
            )
            assert metric(text, "glue_cell_part_dispensing_cv_ratio_sum") == pytest.approx(0.03)
            assert metric(text, "glue_cell_part_trajectory_precision_mm_sum") == 2.5
            assert metric(text, "glue_cell_part_dispensing_cv_percent_sum") == 3.0
            lines = text.splitlines()
            for old, new in (
                ("glue_cell_part_trajectory_precision_mm", "part_trajectory_precision_meters"),
                ("glue_cell_part_dispensing_cv_percent", "glue_cell_part_dispensing_cv_ratio"),
            ):
                [help_line] = [line for line in lines if line.startswith(f"# HELP {old} ")]
                assert "DEPRECATED" in help_line and new in help_line, help_line

            # The standard collectors, on the cell's own registry.
            assert metric(text, "process_resident_memory_bytes") > 0
            assert metric(text, "process_cpu_seconds_total") >= 0
            assert "python_gc_objects_collected_total{generation=" in text
            assert f'python_info{{implementation="{platform.python_implementation()}"' in text

            [build] = [line for line in lines if line.startswith("glue_cell_build_info{")]
            assert build.endswith(" 1.0"), build
            assert f'version="{package_version()}"' in build
            assert f'python_version="{platform.python_version()}"' in build
            assert 'revision="' in build

            # Each plant link.
            assert metric(text, "glue_cell_mqtt_reconnects_total") == 0
            assert metric(text, "glue_cell_mqtt_messages_dropped_total") == 0
            assert metric(text, "glue_cell_mqtt_backlog_messages") >= 0
            assert metric(text, 'glue_cell_webhook_queued_notices{webhook="mes"}') >= 0
            assert webhook_address not in text and "never-in-metrics" not in text

            # The OPC UA client has gone: its session is no longer counted.
            await until_metric(rig, "glue_cell_opcua_sessions", 0.0)
