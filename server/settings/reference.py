"""What a person needs to know about each setting, read from the Settings model itself.

Why derived and not written down: docs/settings.md, the start-up error for a
bad value and the warning for a misspelt variable all say what a setting
accepts and where it is read from; reading it from the model (its bounds, its
description, the environment names pydantic-settings looks up) keeps the three
true as settings are added. The groups are the model's own section comments
(`# Safety (seconds)`), so the model stays the one place they are written.
"""

from __future__ import annotations

import ast
import inspect
import json
import textwrap
from dataclasses import dataclass
from functools import cache
from typing import Any

from pydantic_settings import EnvSettingsSource

from server.settings.model import Settings

CONFIG_FILE_VARIABLE = "GLUE_APP_CONFIG_PATH"
ENV_PREFIX = "GLUE_APP_"


@dataclass(frozen=True)
class SettingFacts:
    """One setting as docs/settings.md and the start-up messages describe it."""

    name: str
    group: str
    variables: tuple[str, ...]  # environment variables, the GLUE_APP_ one first
    default: str
    accepted: str
    meaning: str


def _number(value: float) -> str:
    return str(int(value)) if float(value).is_integer() else f"{value:g}"


def number_range(bounds: dict[str, Any]) -> str:
    """A schema's numeric bounds as `> 0 .. 744` (`>`/`<` for exclusive bounds)."""
    if "exclusiveMinimum" in bounds:
        low = f"> {_number(bounds['exclusiveMinimum'])}"
    else:
        low = _number(bounds["minimum"]) if "minimum" in bounds else "any"
    if "exclusiveMaximum" in bounds:
        high = f"< {_number(bounds['exclusiveMaximum'])}"
    else:
        high = _number(bounds["maximum"]) if "maximum" in bounds else "any"
    return f"{low} .. {high}"


def _accepted(schema: dict[str, Any]) -> str:
    """What a value must be, from the field's JSON schema, in a person's words."""
    if "accepts" in schema:  # said by the field itself, optional or not (json_schema_extra)
        return str(schema["accepts"])
    options = [o for o in schema.get("anyOf", [schema]) if o.get("type") != "null"]
    optional = len(options) < len(schema.get("anyOf", [schema]))
    texts = [_accepted_one(option) for option in options]
    text = " or ".join(texts)
    return f"{text}, or unset" if optional else text


def _accepted_one(schema: dict[str, Any]) -> str:
    if "accepts" in schema:  # said by the field itself (json_schema_extra)
        return str(schema["accepts"])
    kind = schema.get("type")
    if "enum" in schema:
        return "one of " + ", ".join(str(v) for v in schema["enum"])
    if kind == "boolean":
        return "true or false"
    if kind == "integer":
        return f"an integer {number_range(schema)}"
    if kind == "number":
        return f"a number {number_range(schema)}"
    if kind == "array":
        items = schema.get("prefixItems")
        if items:
            ranges = " / ".join(dict.fromkeys(number_range(i) for i in items))
            return f"a JSON list of {len(items)} numbers, each {ranges}"
        inner = schema.get("items", {})
        if inner.get("prefixItems"):
            pair = inner["prefixItems"]
            ranges = " / ".join(dict.fromkeys(number_range(i) for i in pair))
            return f"a JSON list of [x, y] pairs, each number {ranges}"
        return "a JSON list of strings"
    if schema.get("format") == "path":
        return "a path"
    return "text"


def _default(name: str) -> str:
    field = Settings.model_fields[name]
    extra = field.json_schema_extra
    if isinstance(extra, dict) and "default_text" in extra:  # a default that depends on the host
        return str(extra["default_text"])
    factory = field.default_factory
    value = factory() if factory is not None else field.default  # type: ignore[call-arg]
    if value is None:
        return "unset"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return _number(value)
    if isinstance(value, tuple | list):
        return json.dumps(value, default=str).replace(".0,", ",").replace(".0]", "]")
    return str(value)


@cache
def variables_by_setting() -> dict[str, tuple[str, ...]]:
    """Each setting's environment variables, as pydantic-settings looks them up.

    Asked of pydantic-settings itself (aliases such as ROBOT_IP and
    GLUE_APP_LOG_LEVEL included) rather than rebuilt from the prefix, so the
    documentation and the unknown-variable check agree with what is read.
    """
    source = EnvSettingsSource(Settings)
    names: dict[str, tuple[str, ...]] = {}
    for name, field in Settings.model_fields.items():
        found = dict.fromkeys(
            env_name.upper() for _, env_name, _ in source._extract_field_info(field, name)
        )
        prefixed = [n for n in found if n.startswith(ENV_PREFIX)]
        plain = [n for n in found if not n.startswith(ENV_PREFIX)]
        names[name] = tuple(sorted(prefixed, key=len, reverse=True) + plain)
    return names


def known_variables() -> set[str]:
    """Every environment variable the server reads for its settings."""
    return {v for names in variables_by_setting().values() for v in names} | {CONFIG_FILE_VARIABLE}


@cache
def groups() -> dict[str, str]:
    """Each field's section: the comment line above the first field of each section."""
    source = textwrap.dedent(inspect.getsource(Settings))
    lines = source.splitlines()
    tree = ast.parse(source)
    body = tree.body[0]
    assert isinstance(body, ast.ClassDef)
    group, previous_end, found = "General", 0, {}
    for node in body.body:
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            between = lines[previous_end : node.lineno - 1]
            comments = [ln.strip()[1:].strip() for ln in between if ln.strip().startswith("#")]
            if comments:
                group = comments[0]
            found[node.target.id] = group
        previous_end = node.end_lineno or node.lineno
    for base in Settings.__mro__[1:]:  # a section model among the bases: its docstring
        if base.__module__.startswith("server.settings.") and base.__doc__:
            title = base.__doc__.strip().splitlines()[0].rstrip(".")
            for name in getattr(base, "__annotations__", {}):
                found.setdefault(name, title)
    return found


def facts() -> list[SettingFacts]:
    """Every setting, in the model's order."""
    schema = Settings.model_json_schema()["properties"]
    sections = groups()
    variables = variables_by_setting()
    return [
        SettingFacts(
            name=name,
            group=sections.get(name, "General"),
            variables=variables[name],
            default=_default(name),
            accepted=_accepted(schema[name]),
            meaning=field.description or "",
        )
        for name, field in _in_order()
    ]


def _in_order() -> list[tuple[str, Any]]:
    """The model's fields, those declared in Settings itself first (in its order), then
    those of its section models: the sections of the reference follow the model's own."""
    own = set(Settings.__annotations__)
    fields = list(Settings.model_fields.items())
    return [f for f in fields if f[0] in own] + [f for f in fields if f[0] not in own]


def facts_of(name: str) -> SettingFacts:
    return next(f for f in facts() if f.name == name)
