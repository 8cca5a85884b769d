"""Loading the settings at start-up, with messages a technician can act on.

Why not just `Settings()`: what it raises is written for a programmer. A list
setting given in the environment as something other than JSON raised a
16-line traceback (pydantic-settings' SettingsError); a plain bad number named
the field but not the variable that carried it, nor what it accepts; and a
misspelt `GLUE_APP_*` variable was silently ignored, so the cell ran on the
default the person believed they had changed. Here each refusal is one line
naming the variable (or the config file's key) and what the setting accepts,
and each `GLUE_APP_*` variable that names no setting is a warning naming the
closest one.
"""

from __future__ import annotations

import difflib
import os
import re
from collections.abc import Mapping
from typing import Any

from pydantic import ValidationError
from pydantic_settings import SettingsError

from server.common.errors import ConfigurationError
from server.settings.model import Settings
from server.settings.reference import (
    CONFIG_FILE_VARIABLE,
    ENV_PREFIX,
    facts_of,
    known_variables,
    variables_by_setting,
)

DOCS = "docs/settings.md"

# Variables of the specification's deployment example that this cell does not read,
# and why: a "did you mean" naming an unrelated setting would mislead.
SPECIFICATION_ONLY = {
    "GLUE_APP_THREAD_POOL_SIZE": "the cell runs one event loop and no thread pool of its own",
}
DIFFERENCES = "docs/specification-differences.md"


class SettingsRefused(ConfigurationError):
    """The settings cannot be loaded; the message is one line for the console."""


def load_settings(overrides: Mapping[str, Any] | None = None) -> Settings:
    """`Settings(**overrides)`, or SettingsRefused with one line saying what to change."""
    given = dict(overrides or {})
    try:
        return Settings(**given)
    except ValidationError as exc:
        raise SettingsRefused(_validation_problem(exc, given)) from None
    except SettingsError as exc:  # a list or tuple in the environment that is not JSON
        raise SettingsRefused(_parse_problem(exc)) from None
    except ConfigurationError as exc:  # the config file itself (missing, not JSON)
        raise SettingsRefused(str(exc)) from None


def unknown_variables(environ: Mapping[str, str] | None = None) -> list[str]:
    """A warning for each GLUE_APP_* variable that no setting reads, naming the closest."""
    environ = os.environ if environ is None else environ
    known = known_variables()
    candidates = sorted(v for v in known if v.startswith(ENV_PREFIX))
    warnings = []
    for name in sorted(environ):
        upper = name.upper()
        if not upper.startswith(ENV_PREFIX) or upper in known:
            continue
        if upper in SPECIFICATION_ONLY:
            why = SPECIFICATION_ONLY[upper]
            warnings.append(f"{name} is not read: {why} (see {DIFFERENCES})")
            continue
        close = difflib.get_close_matches(upper, candidates, n=1, cutoff=0.6)
        hint = f"; did you mean {close[0]}?" if close else f"; the settings are in {DOCS}"
        warnings.append(f"{name} names no setting and is ignored{hint}")
    return warnings


def _source_of(name: str, given: Mapping[str, Any]) -> str:
    """Where the bad value of setting `name` came from, highest priority first."""
    if name in given:
        return f"{name} (command line)"
    environ = {k.upper(): v for k, v in os.environ.items()}
    for variable in variables_by_setting().get(name, ()):
        if variable in environ:
            if holds_secrets(name):  # never echoed: the message goes to the console and log
                return f"{variable} (value not shown: it holds secrets)"
            return f"{variable}={environ[variable]!r}"
    config = os.environ.get(CONFIG_FILE_VARIABLE)
    return f"{name} in {config}" if config else name


def holds_secrets(name: str) -> bool:
    """Whether setting `name` may hold a secret (its value is then never repeated)."""
    extra = Settings.model_fields[name].json_schema_extra
    return isinstance(extra, dict) and bool(extra.get("holds_secrets"))


def _accepts(name: str) -> str:
    facts = facts_of(name)
    return f"{name} accepts {facts.accepted} ({DOCS})"


def _validation_problem(exc: ValidationError, given: Mapping[str, Any]) -> str:
    first = exc.errors()[0]
    more = exc.error_count() - 1
    tail = f" (and {more} more)" if more else ""
    loc = first["loc"]
    name = str(loc[0]) if loc else ""
    if first["type"] == "extra_forbidden":
        close = difflib.get_close_matches(name, list(Settings.model_fields), n=1)
        hint = f"; did you mean {close[0]}?" if close else f"; the settings are in {DOCS}"
        return f"{name} in {os.environ.get(CONFIG_FILE_VARIABLE)} names no setting{hint}{tail}"
    if name not in Settings.model_fields:  # a rule across settings: its message names them
        return f"invalid settings: {first['msg'].removeprefix('Value error, ')}{tail}"
    where = f" item {', '.join(str(part) for part in loc[1:])}" if loc[1:] else ""
    message = first["msg"].removeprefix("Value error, ")
    return f"{_source_of(name, given)}{where}: {message}; {_accepts(name)}{tail}"


def _parse_problem(exc: SettingsError) -> str:
    match = re.search(r'field "(\w+)"', str(exc))
    if not match or match.group(1) not in Settings.model_fields:
        return f"invalid settings: {exc}"
    name = match.group(1)
    return f"{_source_of(name, {})} is not valid JSON; {_accepts(name)}"
