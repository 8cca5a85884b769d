"""The settings by concern: every field in one section, each component reading only its own.

`Settings` composes the sections (server/settings/<section>.py) by inheritance, so
the loader, the environment names and the JSON file see one flat model; these tests
check the composition stays a partition and that a component typed to take a
section reads nothing outside it.
"""

from __future__ import annotations

import ast
import json
from collections import Counter
from pathlib import Path

import pytest
from pydantic import BaseModel, Field, ValidationError

from server.settings.glue import GlueSettings
from server.settings.load import load_settings
from server.settings.model import Settings, sections
from server.settings.mqtt import MqttSettings
from server.settings.quality import QualitySettings
from server.settings.reference import declared_fields
from server.settings.robot import RobotSettings
from server.settings.section import title_of

pytestmark = pytest.mark.unit

SERVER = Path(__file__).resolve().parents[2] / "server"
SECTIONS = {section.__name__: section for section in sections()}


def test_every_field_is_declared_in_exactly_one_section() -> None:
    declared = Counter(name for section in sections() for name in declared_fields(section))
    assert [name for name, count in declared.items() if count > 1] == []
    assert set(declared) == set(Settings.model_fields)
    assert not Settings.__annotations__.keys() & Settings.model_fields.keys(), (
        "Settings declares fields of its own: they belong in a section"
    )


def test_each_section_is_its_own_module_under_server_settings() -> None:
    modules = [section.__module__ for section in sections()]
    assert len(modules) == len(set(modules))
    assert all(m.startswith("server.settings.") for m in modules)
    assert all(title_of(section) for section in sections())


def test_a_plain_basemodel_base_is_a_section_too() -> None:
    class ModbusGatewaySettings(BaseModel):
        gateway_port: int = Field(502, description="the gateway's TCP port")

    class Extended(ModbusGatewaySettings, Settings):
        pass

    assert title_of(ModbusGatewaySettings) == "Modbus gateway"
    assert title_of(RobotSettings) == "Robot"
    assert declared_fields(ModbusGatewaySettings) == ("gateway_port",)
    assert Extended(gateway_port=5020).section(ModbusGatewaySettings).gateway_port == 5020


def test_a_section_is_a_frozen_copy_of_the_values_in_force() -> None:
    settings = Settings(robot_ip="10.0.0.5", shift_hours=12)
    robot = settings.section(RobotSettings)
    assert type(robot) is RobotSettings
    assert robot.robot_ip == "10.0.0.5" and not robot.robot_simulated
    assert robot.model_fields_set == {"robot_ip"}
    with pytest.raises(ValidationError):
        robot.robot_port = 1  # type: ignore[misc]
    settings.inspection_enabled = False  # as PATCH /settings changes it
    assert settings.section(QualitySettings).inspection_enabled is False
    assert robot.model_dump() == {n: getattr(settings, n) for n in RobotSettings.model_fields}


def test_a_section_validates_alone_as_the_loader_does() -> None:
    with pytest.raises(ValidationError, match="glue_link_timeout"):
        GlueSettings(glue_link_timeout=0.1, glue_poll_interval=0.2)
    with pytest.raises(ValidationError, match="glue_link_timeout"):
        Settings(glue_link_timeout=0.1, glue_poll_interval=0.2)
    with pytest.raises(ValidationError):
        MqttSettings(mqtt_reconnect_max=float("nan"))


def test_environment_names_and_the_json_file_are_the_flat_names(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    config = tmp_path / "config.json"
    config.write_text(json.dumps({"shift_hours": 10, "mqtt_topic_prefix": "plant"}))
    monkeypatch.setenv("GLUE_APP_CONFIG_PATH", str(config))
    monkeypatch.setenv("ROBOT_IP", "192.0.2.7")
    monkeypatch.setenv("GLUE_CONTROLLER_PORT", "tcp://192.0.2.8:502")
    monkeypatch.setenv("VISION_CAMERA_ID", "sim")
    monkeypatch.setenv("GLUE_APP_GLUE_POLL_INTERVAL", "0.2")
    settings = load_settings({"data_path": tmp_path})
    assert settings.robot_ip == "192.0.2.7"
    assert settings.section(GlueSettings).glue_controller_port == "tcp://192.0.2.8:502"
    assert settings.glue_poll_interval == 0.2
    assert settings.shift_hours == 10 and settings.mqtt_topic_prefix == "plant"


def _section_of(annotation: ast.expr | None) -> type[BaseModel] | None:
    if isinstance(annotation, ast.Name):
        return SECTIONS.get(annotation.id)
    if isinstance(annotation, ast.Constant) and isinstance(annotation.value, str):
        return SECTIONS.get(annotation.value)
    return None


def _reads(node: ast.AST, name: str) -> set[str]:
    """Attributes read of the local `name` (`name.x`) within `node`."""
    return {
        sub.attr
        for sub in ast.walk(node)
        if isinstance(sub, ast.Attribute)
        and isinstance(sub.value, ast.Name)
        and sub.value.id == name
    }


def _self_reads(node: ast.AST, attribute: str) -> set[str]:
    """Attributes read of `self.<attribute>` (`self.a.x`, or `s = self.a` then `s.x`)."""
    found: set[str] = set()
    for sub in ast.walk(node):
        if (
            isinstance(sub, ast.Attribute)
            and isinstance(sub.value, ast.Attribute)
            and isinstance(sub.value.value, ast.Name)
            and sub.value.value.id == "self"
            and sub.value.attr == attribute
        ):
            found.add(sub.attr)
        if (
            isinstance(sub, ast.Assign)
            and isinstance(sub.value, ast.Attribute)
            and isinstance(sub.value.value, ast.Name)
            and sub.value.value.id == "self"
            and sub.value.attr == attribute
        ):
            for target in sub.targets:
                if isinstance(target, ast.Name):
                    found |= _reads(node, target.id)
    return found


def _uses_of_sections() -> list[tuple[str, type[BaseModel], set[str]]]:
    """(where, section, attributes read) for every parameter typed as a section, and every
    `self.<attribute>` a constructor sets from one, across server/."""
    uses = []
    for path in sorted(SERVER.rglob("*.py")):
        if path.is_relative_to(SERVER / "settings"):
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for cls in [n for n in ast.walk(tree) if isinstance(n, ast.ClassDef)]:
            init = next(
                (f for f in cls.body if isinstance(f, ast.FunctionDef) and f.name == "__init__"),
                None,
            )
            if init is None:
                continue
            typed = {a.arg: _section_of(a.annotation) for a in init.args.args}
            for stmt in ast.walk(init):
                if (
                    isinstance(stmt, ast.Assign)
                    and isinstance(stmt.value, ast.Name)
                    and typed.get(stmt.value.id) is not None
                ):
                    section = typed[stmt.value.id]
                    assert section is not None
                    for target in stmt.targets:
                        if isinstance(target, ast.Attribute):
                            where = f"{path.relative_to(SERVER)}: {cls.name}.{target.attr}"
                            uses.append((where, section, _self_reads(cls, target.attr)))
        for func in [
            n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef)
        ]:
            arguments = func.args.args + func.args.kwonlyargs
            for argument in arguments:
                section = _section_of(argument.annotation)
                if section is not None:
                    where = f"{path.relative_to(SERVER)}: {func.name}({argument.arg})"
                    uses.append((where, section, _reads(func, argument.arg)))
    return uses


def _carried(section: type[BaseModel]) -> set[str]:
    """What an instance of `section` answers: its fields, properties and methods."""
    return set(section.model_fields) | set(dir(section))


def test_components_typed_to_a_section_read_only_what_it_carries() -> None:
    uses = _uses_of_sections()
    # The components the composition root hands a section to are among them.
    wheres = " ".join(where for where, _, _ in uses)
    components = ("Access", "MqttLink", "OpcUaInterface", "Notifier", "Deliverer", "glue_of")
    for component in components:
        assert component in wheres, component
    outside = [
        f"{where} reads {sorted(read - _carried(section))} not in {section.__name__}"
        for where, section, read in uses
        if read - _carried(section)
    ]
    assert outside == []
