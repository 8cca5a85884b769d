"""Settings changed at runtime stay: saved in the data directory, put back in force at a
restart, named as such by GET /settings; a setting that needs a restart is refused
with that reason."""

from __future__ import annotations

import json
import stat

from tests.integration.test_gluectl import gluectl_process
from tests.rig import open_rig


async def test_a_runtime_change_survives_a_restart_and_says_where_it_comes_from(
    tmp_path, monkeypatch
) -> None:
    data = tmp_path / "data"
    monkeypatch.setenv("GLUE_APP_DESIGN_CYCLE_TIME_S", "40")
    async with open_rig(data) as rig:
        before = (await rig.api.get("/settings")).json()
        assert before["shift_hours"] == 8.0
        assert before["sources"]["shift_hours"] == "default"
        assert before["sources"]["design_cycle_time_s"] == "environment"
        assert "shift_hours" in before["runtime_settings"]
        assert "robot_ip" not in before["runtime_settings"]
        changed = await rig.api.patch("/settings", json={"shift_hours": 10})
        assert changed.status_code == 200, changed.text
        assert changed.json()["changed"] == {"shift_hours": {"old": 8.0, "new": 10.0}}
        now = (await rig.api.get("/settings")).json()
        assert now["shift_hours"] == 10.0 and now["sources"]["shift_hours"] == "runtime"
    saved = data / "runtime-settings.json"
    assert json.loads(saved.read_text(encoding="utf-8")) == {"shift_hours": 10.0}
    assert stat.S_IMODE(saved.stat().st_mode) == 0o600
    async with open_rig(data) as rig:  # the same data directory: a restart
        after = (await rig.api.get("/settings")).json()
        assert after["shift_hours"] == 10.0
        assert after["sources"]["shift_hours"] == "runtime"
        assert after["sources"]["design_cycle_time_s"] == "environment"
        # a later change keeps the earlier one in the file
        await rig.api.patch("/settings", json={"order_defect_limit": 5})
        audit = (await rig.api.get("/audit", params={"limit": 100})).json()["audit"]
        assert any(
            row["action"] == "PATCH /settings" and "order_defect_limit" in row["detail"]
            for row in audit
        )
    assert json.loads(saved.read_text(encoding="utf-8")) == {
        "order_defect_limit": 5,
        "shift_hours": 10.0,
    }


async def test_a_setting_that_needs_a_restart_is_refused_with_that_reason(tmp_path) -> None:
    async with open_rig(tmp_path / "data") as rig:
        refused = await rig.api.patch("/settings", json={"robot_ip": "10.0.0.1"})
        assert refused.status_code == 422
        detail = refused.json()["detail"]
        assert "robot_ip takes effect only at a restart" in detail
        assert "ROBOT_IP" in detail and "Extra inputs" not in detail
        unknown = await rig.api.patch("/settings", json={"no_such_setting": 1})
        assert unknown.status_code == 422 and "no_such_setting" in unknown.json()["detail"]
        settings = (await rig.api.get("/settings")).json()
        assert settings["robot_ip"] == "127.0.0.1"  # unchanged
    assert not (tmp_path / "data" / "runtime-settings.json").exists()


async def test_a_saved_value_the_settings_now_refuse_is_left_out(tmp_path) -> None:
    data = tmp_path / "data"
    async with open_rig(data):
        pass
    (data / "runtime-settings.json").write_text(
        json.dumps({"shift_hours": -3, "robot_ip": "10.0.0.9", "order_defect_limit": 4})
    )
    async with open_rig(data) as rig:
        settings = (await rig.api.get("/settings")).json()
        assert settings["shift_hours"] == 8.0 and settings["sources"]["shift_hours"] == "default"
        assert settings["robot_ip"] == "127.0.0.1"
        assert settings["order_defect_limit"] == 4
        assert settings["sources"]["order_defect_limit"] == "runtime"


async def test_gluectl_settings_get_and_set(tmp_path) -> None:
    data = tmp_path / "data"
    async with open_rig(data) as rig:
        url = str(rig.api.base_url).rstrip("/")
        base = ("--url", url, "--data-dir", str(data))
        changed = await gluectl_process(*base, "settings", "set", "shift_hours=10")
        assert changed.code == 0, changed.stderr
        assert changed.stdout.strip() == "shift_hours: 8 -> 10 (saved)"
        shown = await gluectl_process(*base, "settings", "get", "shift_hours", "robot_ip")
        assert shown.code == 0, shown.stderr
        lines = {line.split()[1]: line for line in shown.stdout.splitlines() if "│" in line}
        assert "10" in lines["shift_hours"] and "runtime" in lines["shift_hours"]
        assert "at once" in lines["shift_hours"] and "at a restart" in lines["robot_ip"]
        as_json = await gluectl_process(*base, "--json", "settings", "get", "shift_hours")
        assert as_json.json() == [
            {"name": "shift_hours", "value": 10.0, "source": "runtime", "changes": "at once"}
        ]
        refused = await gluectl_process(*base, "settings", "set", "robot_ip=10.0.0.1")
        assert refused.code == 6
        assert "robot_ip takes effect only at a restart" in refused.stderr
        unknown = await gluectl_process(*base, "settings", "get", "no_such_setting")
        assert unknown.code == 2 and "no_such_setting names no setting" in unknown.stderr
