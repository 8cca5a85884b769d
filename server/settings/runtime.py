"""Which settings change at runtime, where each value in force came from, and how the
changes saved in the data directory are put back in force at start-up.

Precedence: a setting changed at runtime (PATCH /settings, saved in
`runtime-settings.json` under the data directory) stands over the environment,
the config file and the default. Why: it is the latest deliberate, audited
decision about this cell, made by someone looking at it; a restart must not
undo it silently. The start-up log names each saved change that stands over a
configured value, and GET /settings names each value's source, so a technician
who sets `GLUE_APP_SHIFT_HOURS` and sees another figure finds why at once;
setting the value again at runtime (or removing the file) ends it.

A setting that is not in RUNTIME_SETTINGS takes effect only at a restart: PATCH
refuses it with that reason, and a saved file naming one is ignored loudly.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, Literal

from pydantic import ValidationError

from server.settings.model import Settings
from server.settings.reference import CONFIG_FILE_VARIABLE, variables_by_setting

RUNTIME_SETTINGS = (
    "error_state_timeout",
    "auto_recovery_enabled",
    "error_recovery_attempts",
    "error_recovery_delay",
    "calibration_max_error_mm",
    "design_cycle_time_s",
    "shift_hours",
    "processing_timeout",
    "logging_level",
    # The quality engineer's: whether parts are judged, and against what (docs/quality.md)
    "inspection_enabled",
    "trajectory_precision_limit_mm",
    "dispensing_flow_tolerance_percent",
    "dispensing_max_out_of_tolerance_s",
    "glue_volume_tolerance_percent",
    "bead_width_tolerance_percent",
    "bead_max_gap_mm",
    "bead_max_offset_mm",
    "order_defect_limit",
)

Source = Literal["runtime", "command line", "environment", "file", "default"]


def restart_reason(name: str) -> str:
    """Why PATCH /settings refuses setting `name`, and how to change it instead."""
    variables = variables_by_setting().get(name, ())
    where = f"{' or '.join(variables)} in the environment" if variables else "the environment"
    return (
        f"{name} takes effect only at a restart: set {where} or `{name}` in the config "
        f"file ({CONFIG_FILE_VARIABLE}), then restart the server (docs/settings.md)"
    )


def restore_saved(settings: Settings, saved: Mapping[str, Any]) -> tuple[list[str], list[str]]:
    """Put the saved runtime changes in force on `settings`: (names applied, problems).

    Each saved value is checked like a PATCH, against the whole model (a value the
    model now refuses, say after a bound was tightened, is left out and said); a
    name that is not a runtime setting is left out and said. Nothing raises: a
    damaged change must not stop the cell from starting on its configuration.
    """
    problems = [
        f"{name} is not a setting changed at runtime; ignored"
        for name in saved
        if name not in RUNTIME_SETTINGS
    ]
    wanted = {name: value for name, value in saved.items() if name in RUNTIME_SETTINGS}
    applied = []
    for name, value in wanted.items():
        try:
            merged = Settings.model_validate({**settings.model_dump(), name: value})
        except ValidationError as exc:
            why = "; ".join(error["msg"] for error in exc.errors())
            problems.append(f"{name}={value!r} is not put in force: {why}")
            continue
        setattr(settings, name, getattr(merged, name))
        applied.append(name)
    return applied, problems


def _config_file_keys() -> set[str]:
    """The keys of the JSON config file named by GLUE_APP_CONFIG_PATH (none: empty)."""
    path = os.environ.get(CONFIG_FILE_VARIABLE)
    if not path:
        return set()
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return set()
    return set(data) if isinstance(data, dict) else set()


def sources_of(settings: Settings, runtime: Iterable[str]) -> dict[str, Source]:
    """Where each setting's value in force comes from, highest priority first.

    `runtime`: the names changed at runtime (saved or patched since). A value given
    as a keyword argument is the command line's (`--data-dir`); the environment and
    the config file are looked up as pydantic-settings reads them.
    """
    changed = set(runtime)
    environ = {key.upper() for key in os.environ}
    in_file = _config_file_keys()
    variables = variables_by_setting()
    sources: dict[str, Source] = {}
    for name in Settings.model_fields:
        if name in changed:
            sources[name] = "runtime"
        elif any(variable in environ for variable in variables.get(name, ())):
            sources[name] = "environment"
        elif name in in_file:
            sources[name] = "file"
        elif name in settings.model_fields_set:
            sources[name] = "command line"
        else:
            sources[name] = "default"
    return sources
