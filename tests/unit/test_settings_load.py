"""Start-up settings messages: one line naming the variable and what it accepts, and a
warning naming the closest setting for a GLUE_APP_ variable no setting reads."""

from __future__ import annotations

import json
import re

import pytest
from pydantic import ValidationError

from server.settings.load import SettingsRefused, load_settings, unknown_variables
from server.settings.model import Settings
from server.settings.reference import facts, known_variables, variables_by_setting


@pytest.mark.parametrize(
    ("variable", "value", "accepts"),
    [
        ("GLUE_APP_SHIFT_HOURS", "abc", "shift_hours accepts a number 0.25 .. 744"),
        ("GLUE_APP_SHIFT_HOURS", "1e9", "shift_hours accepts a number 0.25 .. 744"),
        ("GLUE_APP_SAFE_POSITION", "abc", "safe_position accepts a JSON list of 6 numbers"),
        ("GLUE_APP_TRUSTED_PROXIES", "10.0.0.1", "trusted_proxies accepts a JSON list"),
        ("GLUE_APP_LOG_LEVEL", "loud", "logging_level accepts one of DEBUG, INFO"),
        ("GLUE_APP_AUTO_RECOVERY_ENABLED", "maybe", "accepts true or false"),
    ],
)
def test_a_bad_value_is_one_line_naming_the_variable_and_what_it_accepts(
    monkeypatch, variable: str, value: str, accepts: str
) -> None:
    monkeypatch.setenv(variable, value)
    with pytest.raises(SettingsRefused) as refused:
        load_settings()
    message = str(refused.value)
    assert "\n" not in message
    assert message.startswith(f"{variable}={value!r}"), message
    assert accepts in message and "docs/settings.md" in message


def test_a_bad_key_in_the_config_file_names_the_file_and_the_closest_setting(
    tmp_path, monkeypatch
) -> None:
    config = tmp_path / "config.json"
    config.write_text(json.dumps({"event_queue_sise": 5}))
    monkeypatch.setenv("GLUE_APP_CONFIG_PATH", str(config))
    with pytest.raises(SettingsRefused, match="did you mean event_queue_size"):
        load_settings()
    config.write_text(json.dumps({"shift_hours": "long"}))
    with pytest.raises(
        SettingsRefused, match=f"shift_hours in {re.escape(str(config))}: .* accepts a number"
    ):
        load_settings()
    monkeypatch.setenv("GLUE_APP_CONFIG_PATH", str(tmp_path / "missing.json"))
    with pytest.raises(SettingsRefused, match="does not exist"):
        load_settings()


def test_a_rule_across_settings_says_which_settings() -> None:
    with pytest.raises(SettingsRefused, match=r"default_pressure_psi .* glue_pressure_range_psi"):
        load_settings({"default_pressure_psi": 100})


def test_an_unknown_glue_app_variable_is_a_warning_naming_the_closest_setting() -> None:
    environ = {
        "GLUE_APP_SHIFT_HOUR": "12",  # a typo of a setting
        "GLUE_APP_SHIFT_HOURS": "12",  # known
        "GLUE_APP_LOG_LEVEL": "INFO",  # known, an alias
        "GLUE_APP_CONFIG_PATH": "x.json",  # known, not a setting
        "GLUE_APP_ZZZZZZZZZZZZZZZZZZ": "1",  # nothing close
        "ROBOT_IP": "sim",  # not GLUE_APP_: not ours to judge
        "PATH": "/bin",
    }
    warnings = unknown_variables(environ)
    assert warnings == [
        "GLUE_APP_SHIFT_HOUR names no setting and is ignored; did you mean GLUE_APP_SHIFT_HOURS?",
        "GLUE_APP_ZZZZZZZZZZZZZZZZZZ names no setting and is ignored; the settings are in "
        "docs/settings.md",
    ]


def test_the_specifications_unread_variables_say_why_not_what_else() -> None:
    """The deployment example's variable the cell does not read gets a reason, not a
    "did you mean" naming an unrelated setting (GLUE_APP_TRUSTED_PROXIES, once); its
    memory limit is a setting the cell reads."""
    warnings = unknown_variables(
        {"GLUE_APP_MEMORY_LIMIT": "512MB", "GLUE_APP_THREAD_POOL_SIZE": "4"}
    )
    assert len(warnings) == 1 and warnings[0].startswith("GLUE_APP_THREAD_POOL_SIZE ")
    for warning in warnings:
        assert "is not read: " in warning and "did you mean" not in warning
        assert warning.endswith("(see docs/specification-differences.md)")


def test_every_variable_listed_is_one_the_settings_read(monkeypatch) -> None:
    """The documented variables are those pydantic-settings reads: each one takes effect."""
    for name, variables in variables_by_setting().items():
        if name == "logging_level":
            for variable in variables:
                monkeypatch.setenv(variable, "DEBUG")
                assert load_settings().logging_level == "DEBUG", variable
                monkeypatch.delenv(variable)
    assert "GLUE_APP_SHIFT_HOURS" in known_variables() and "ROBOT_IP" in known_variables()


def test_every_setting_has_a_meaning_a_group_and_what_it_accepts() -> None:
    for setting in facts():
        assert setting.meaning and setting.accepted and setting.group, setting
        assert setting.variables[0] == f"GLUE_APP_{setting.name.upper()}", setting


def test_the_specifications_memory_limit_is_read(monkeypatch) -> None:
    """GLUE_APP_MEMORY_LIMIT (Appendix A: 512MB) is the self-watch's memory_limit."""
    assert Settings().memory_limit == "512MB"
    monkeypatch.setenv("GLUE_APP_MEMORY_LIMIT", "1GB")
    assert Settings().memory_limit == "1GB"
    monkeypatch.setenv("GLUE_APP_MEMORY_LIMIT", "a lot")
    with pytest.raises(ValidationError, match="memory_limit"):
        Settings()
