"""Settings come from defaults, a JSON file, environment variables and arguments."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from pydantic import ValidationError

from server.settings.model import Settings, marker_layout_problems
from server.settings.reference import facts
from tests.schema_bounds import unbounded_numbers


def test_defaults_start_the_simulated_cell() -> None:
    settings = Settings()
    assert settings.robot_simulated and settings.glue_simulated and settings.camera_simulated
    assert settings.event_queue_size == 1000 and settings.robot_port == 30003


def test_json_file_then_environment_then_arguments(tmp_path, monkeypatch) -> None:
    config = tmp_path / "config.json"
    config.write_text(
        json.dumps({"event_queue_size": 50, "processing_timeout": 12, "error_state_timeout": 99})
    )
    monkeypatch.setenv("GLUE_APP_CONFIG_PATH", str(config))
    monkeypatch.setenv("GLUE_APP_EVENT_QUEUE_SIZE", "70")
    monkeypatch.setenv("GLUE_APP_LOG_LEVEL", "DEBUG")
    monkeypatch.setenv("ROBOT_IP", "192.0.2.10")
    monkeypatch.setenv("GLUE_CONTROLLER_PORT", "/dev/ttyUSB1")
    settings = Settings(processing_timeout=5)
    assert settings.event_queue_size == 70  # env beats the file
    assert settings.processing_timeout == 5  # arguments beat everything
    assert settings.error_state_timeout == 99  # the file beats defaults
    assert settings.logging_level == "DEBUG"
    assert settings.robot_ip == "192.0.2.10" and not settings.robot_simulated
    assert settings.glue_controller_port == "/dev/ttyUSB1"


def test_a_bad_value_names_the_key(monkeypatch) -> None:
    monkeypatch.setenv("GLUE_APP_EVENT_QUEUE_SIZE", "0")
    with pytest.raises(ValidationError, match="event_queue_size"):
        Settings()


def test_an_unknown_key_in_the_file_is_refused(tmp_path, monkeypatch) -> None:
    config = tmp_path / "config.json"
    config.write_text(json.dumps({"event_queue_sise": 5}))
    monkeypatch.setenv("GLUE_APP_CONFIG_PATH", str(config))
    with pytest.raises(ValidationError, match="event_queue_sise"):
        Settings()


def test_a_missing_config_file_is_a_clear_error(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("GLUE_APP_CONFIG_PATH", str(tmp_path / "nope.json"))
    with pytest.raises(ValueError, match="does not exist"):
        Settings()


SPECIFICATION_PRODUCTION_CONFIG = {  # Appendix A, as written
    "event_queue_size": 1000,
    "processing_timeout": 60,
    "max_concurrent_operations": 5,
    "error_recovery_attempts": 5,
    "error_recovery_delay": 2.0,
    "auto_recovery_enabled": True,
    "performance_monitoring": True,
    "metrics_collection_interval": 10,
    "performance_history_size": 1000,
    "logging_level": "INFO",
    "log_file_path": "/var/log/glue_application/state_machine.log",
    "log_rotation_size": "10MB",
    "log_retention_days": 30,
    "state_persistence": True,
    "persistence_file": "/var/lib/glue_application/state_machine.json",
    "persistence_interval": 30,
    "broadcast_enabled": True,
    "broadcast_port": 8080,
    "max_broadcast_clients": 10,
    "analytics_enabled": True,
    "analytics_database": "/var/lib/glue_application/analytics.db",
    "analytics_retention_days": 90,
    "robot_communication_timeout": 10,
    "vision_processing_timeout": 5,
    "glue_system_timeout": 15,
    "emergency_stop_timeout": 1,
    "safe_position_timeout": 30,
    "error_state_timeout": 300,
}


def test_the_specifications_production_config_loads_and_says_what_it_ignores(
    tmp_path, monkeypatch
) -> None:
    config = tmp_path / "production.json"
    config.write_text(json.dumps(SPECIFICATION_PRODUCTION_CONFIG))
    monkeypatch.setenv("GLUE_APP_CONFIG_PATH", str(config))
    settings = Settings()
    assert settings.max_broadcast_clients == 10 and settings.error_recovery_attempts == 5
    assert settings.data_file(settings.analytics_database, "journal.db").is_absolute()
    notes = " | ".join(settings.compatibility_notes())
    assert "max_concurrent_operations=5 has no effect" in notes
    assert "broadcast_port=8080 has no effect" in notes
    assert "metrics_collection_interval" in notes


def test_defaults_carry_no_compatibility_notes() -> None:
    assert Settings().compatibility_notes() == []


GRID = [(x, y) for y in (-150.0, 0.0, 150.0) for x in (250.0, 400.0, 550.0)]


def test_a_real_camera_needs_the_marker_layout_set() -> None:
    with pytest.raises(ValidationError, match="marker_positions_mm must be set for a real camera"):
        Settings(vision_camera_id="0")
    assert Settings(vision_camera_id="0", marker_positions_mm=GRID).marker_positions_mm == GRID


def test_a_real_cameras_layout_may_come_from_the_environment(monkeypatch) -> None:
    monkeypatch.setenv("VISION_CAMERA_ID", "0")
    monkeypatch.setenv("GLUE_APP_MARKER_POSITIONS_MM", json.dumps(GRID))
    assert Settings().marker_positions_mm == GRID


def test_a_marker_outside_the_workspace_is_refused_naming_it() -> None:
    layout = [*GRID[:8], (900.0, 150.0)]
    with pytest.raises(ValidationError, match=r"marker_positions_mm: marker 8 at \(900, 150\)"):
        Settings(marker_positions_mm=layout)


def test_overlapping_markers_are_refused() -> None:
    layout = [*GRID[:8], (410.0, 140.0)]
    with pytest.raises(ValidationError, match=r"markers 7 and 8 are 14\.1 mm apart"):
        Settings(marker_positions_mm=layout)


@pytest.mark.parametrize(
    "layout",
    [
        [(150.0 + 60.0 * i, 0.0) for i in range(9)],  # all on one line
        # two off the line: fine, but the hold-out check leaves each out in turn
        [(150.0 + 60.0 * i, 0.0) for i in range(7)] + [(300.0, 200.0), (500.0, -200.0)],
    ],
    ids=["one line", "one marker left out"],
)
def test_a_degenerate_marker_layout_is_refused(layout) -> None:
    with pytest.raises(ValidationError, match="marker_positions_mm: the layout is degenerate"):
        Settings(marker_positions_mm=layout)


def test_a_layout_just_off_one_line_counts_as_on_it() -> None:
    # within marker_size_mm of one line: the homography would be ill-conditioned
    layout = [(150.0 + 60.0 * i, 10.0 * (i % 2)) for i in range(9)]
    with pytest.raises(ValidationError, match="degenerate"):
        Settings(marker_positions_mm=layout)
    Settings(marker_positions_mm=[(x, y + 0.5 * (x % 7)) for x, y in GRID])  # a real, uneven grid


def test_glue_supervision_has_real_defaults() -> None:
    settings = Settings()
    assert settings.glue_pressure_range_psi == (20.0, 60.0)  # not the register's 0-150
    assert settings.glue_flow_deviation_pct == 20.0 and settings.glue_flow_deviation_s == 0.5
    assert settings.glue_temperature_range_c == (10.0, 40.0)
    assert settings.glue_link_timeout == 0.5


def test_glue_supervision_that_would_trip_every_run_is_refused() -> None:
    with pytest.raises(ValidationError, match=r"default_pressure_psi .* glue_pressure_range_psi"):
        Settings(default_pressure_psi=80.0)
    with pytest.raises(ValidationError, match=r"glue_link_timeout .* glue_poll_interval"):
        Settings(glue_link_timeout=0.1, glue_poll_interval=0.2)
    with pytest.raises(ValidationError, match="glue_temperature_range_c"):
        Settings(glue_temperature_range_c=(40.0, 10.0))


def test_every_numeric_setting_has_both_bounds() -> None:
    """Without a maximum, Infinity and 1e400 would get in."""
    schema = Settings.model_json_schema()
    assert unbounded_numbers(schema, schema) == []


# Float settings whose least value is 0 because 0 means something (no delay, every waypoint,
# no pause, on the table), so a subnormal such as 5e-324 means the same and breaks nothing.
ZERO_MEANS_SOMETHING = {
    "error_recovery_delay",
    "plant_progress_interval",
    "dispensing_max_out_of_tolerance_s",
    "spray_height_mm",
    "default_flow_rate_ml_min",
    "default_pressure_psi",
    "camera_calibration_view_interval_s",
    "mqtt_command_max_skew",  # 0: a command may not be ahead of the cell's clock at all
    "rtt_degraded_min_ms",  # 0: a link is degrading on rtt_degraded_factor alone
    "error_rate_alert_per_100",  # 0: any failed operation in a full window is an alert
}


def _float_settings() -> list[str]:
    return [
        name
        for name, field in Settings.model_fields.items()
        if field.annotation in (float, float | None)
    ]


def _least(name: str) -> float | None:
    """A float setting's inclusive lower bound (None: it has an exclusive one)."""
    metadata = Settings.model_fields[name].metadata
    if any(hasattr(m, "gt") for m in metadata):
        return None
    return next(m.ge for m in metadata if hasattr(m, "ge"))


@pytest.mark.parametrize("name", _float_settings())
def test_every_float_setting_has_a_meaningful_least_value(name: str) -> None:
    """A bare `> 0` lets 3.55e-276 in as a shift (every GET /kpis a 500) and 1e-320 as a
    timeout: each least value is inclusive and what the setting's meaning allows."""
    least = _least(name)
    assert least is not None, f"{name}: an exclusive lower bound lets subnormals in"
    if name in ZERO_MEANS_SOMETHING:
        assert least == 0, name
    else:
        assert least >= 0.001, f"{name}: least value {least} is below a millisecond/resolution"


@pytest.mark.parametrize("name", sorted(set(_float_settings()) - ZERO_MEANS_SOMETHING))
def test_a_subnormal_setting_is_refused_naming_it(name: str) -> None:
    with pytest.raises(ValidationError) as refused:
        Settings(**{name: 5e-324})
    assert [error["loc"] for error in refused.value.errors()] == [(name,)]


def test_the_schema_has_no_exclusive_minimum_of_zero() -> None:
    """openapi.json and docs/settings.md are generated from this schema: they show the bounds."""
    text = json.dumps(Settings.model_json_schema())
    assert '"exclusiveMinimum": 0' not in text


@pytest.mark.parametrize("value", ["inf", "-inf", "nan", "1e400", "Infinity"])
def test_a_non_finite_setting_is_refused_from_the_environment(monkeypatch, value) -> None:
    monkeypatch.setenv("GLUE_APP_PROCESSING_TIMEOUT", value)
    with pytest.raises(ValidationError, match="processing_timeout"):
        Settings()


def test_a_non_finite_setting_is_refused_from_the_config_file(tmp_path, monkeypatch) -> None:
    config = tmp_path / "config.json"
    config.write_text(
        '{"error_state_timeout": Infinity, "safe_position": [400, 0, 1e400, 180, 0, 0]}'
    )
    monkeypatch.setenv("GLUE_APP_CONFIG_PATH", str(config))
    with pytest.raises(ValidationError) as refused:
        Settings()
    assert {error["loc"] for error in refused.value.errors()} == {
        ("error_state_timeout",),
        ("safe_position", 2),
    }


def test_the_specifications_defaults_lie_inside_the_bounds() -> None:
    """Each bound added keeps Appendix A's values and this server's own defaults valid."""
    Settings(**SPECIFICATION_PRODUCTION_CONFIG)
    Settings()


def test_an_empty_workspace_is_refused_naming_the_axis() -> None:
    with pytest.raises(ValidationError, match="z: 500 is not below 100"):
        Settings(workspace_min_mm=(100.0, -400.0, 500.0), workspace_max_mm=(800.0, 400.0, 100.0))


def test_a_safe_position_outside_the_workspace_is_refused_naming_the_axis() -> None:
    """It was accepted: `home` was refused, and every run failed into ERROR."""
    with pytest.raises(
        ValidationError, match=r"safe_position is outside the workspace \(x=900.0 mm"
    ):
        Settings(safe_position=(900.0, 0.0, 200.0, 180.0, 0.0, 0.0))


def test_readmes_short_settings_table_agrees_with_docs_settings() -> None:
    """README lists the most used settings and points to docs/settings.md for the rest;
    what it says of each (variable, default, accepted values) is what the model says."""
    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text(encoding="utf-8")
    assert "docs/settings.md" in readme
    rows = [
        [cell.strip() for cell in line.strip("|").split("|")]
        for line in readme.splitlines()
        if line.startswith("| `")
    ]
    settings = {setting.name: setting for setting in facts()}
    listed = [row for row in rows if row[0].strip("`") in settings]
    assert len(listed) >= 5
    for name, variable, default, accepted in listed:
        setting = settings[name.strip("`")]
        assert variable.strip("`") in setting.variables, name
        assert default in (f"`{setting.default}`", "the simulated table"), name
        assert accepted == setting.accepted, name


@pytest.mark.parametrize("url", ["mqtt://broker:99999", "mqtt://broker:0", "mqtts://broker:65536/"])
def test_an_mqtt_port_out_of_range_is_refused_naming_the_setting(url) -> None:
    """99999 crashed the start with a traceback; 0 connected to 1883 without a word."""
    with pytest.raises(ValidationError, match=r"mqtt_url[\s\S]*port must be 1 to 65535"):
        Settings(mqtt_url=url)
    Settings(mqtt_url="mqtt://broker:1884")


@pytest.mark.parametrize("port", ["tcp://127.0.0.1:99999", "tcp://127.0.0.1:0", "tcp://host"])
def test_a_tcp_dispenser_needs_a_port_in_range(port) -> None:
    """A port past 65535 crashed the start with a traceback."""
    with pytest.raises(ValidationError, match="tcp://HOST:PORT, PORT 1 to 65535"):
        Settings(glue_controller_port=port)
    Settings(glue_controller_port="tcp://[::1]:5020")


def test_every_marker_at_fault_is_named_at_once() -> None:
    """A layout with three problems was refused for the first alone."""
    layout = [(50.0, -150.0), *GRID[1:5], (410.0, 10.0), *GRID[6:8], (900.0, 150.0)]
    problems = marker_layout_problems(layout, (100.0, -400.0, -5.0), (800.0, 400.0, 500.0), 30.0)
    assert [p.split(" ")[:2] for p in problems] == [
        ["marker", "0"],
        ["marker", "8"],
        ["markers", "4"],
    ], problems
