"""The one Settings model of the server: every section, loaded together.

Values come, highest priority first, from: keyword arguments (tests and the
command line), `GLUE_APP_*` environment variables, the JSON file named by
`GLUE_APP_CONFIG_PATH`, then the defaults. The keys are the specification's
(Appendix A) so a configuration written for the original application keeps
working; the hardware variables keep their original names (`ROBOT_IP`,
`VISION_CAMERA_ID`, `GLUE_CONTROLLER_PORT`) without the prefix.

Each concern's fields and the validators that read only them are declared in its
section (server/settings/<section>.py, a `Section`); `Settings` inherits them all,
so the loader, the environment names and the JSON file see one flat model, and
keeps the rules that span sections. `Settings.section(GlueSettings)` gives a
component its section alone.

A device address of `sim` means "start the simulator on loopback and talk to
it through the production client", so the default run exercises the same code
path as a real cell.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, model_validator
from pydantic_settings import (
    BaseSettings,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
)

from server.common.errors import ConfigurationError
from server.settings.access import AccessSettings
from server.settings.broadcast import BroadcastSettings
from server.settings.calibration import (
    DEFAULT_MARKER_POSITIONS_MM,
    CalibrationSettings,
    marker_layout_problems,
)
from server.settings.camera import CameraSettings
from server.settings.glue import GlueSettings, parse_tcp_address
from server.settings.http import HttpSettings
from server.settings.kpis import KpiSettings
from server.settings.logs import LogSettings
from server.settings.maintenance import MaintenanceSettings
from server.settings.motion import Millimetres, MotionSettings, outside_workspace
from server.settings.mqtt import MqttSettings
from server.settings.notifications import WebhookSettings
from server.settings.opcua import OpcUaSettings
from server.settings.plant import PlantSettings, default_cell_id
from server.settings.quality import QualitySettings
from server.settings.recording import RecordingSettings
from server.settings.robot import RobotSettings
from server.settings.run_end import RunEndSettings
from server.settings.safety import SafetySettings
from server.settings.section import SIMULATED
from server.settings.simulation import SimulationSettings
from server.settings.sparkplug import SparkplugSettings
from server.settings.storage import StorageSettings
from server.settings.watch import WatchSettings
from server.settings.worker import WorkerSettings

__all__ = [
    "DEFAULT_MARKER_POSITIONS_MM",
    "SIMULATED",
    "JsonFileSource",
    "Millimetres",
    "Settings",
    "default_cell_id",
    "marker_layout_problems",
    "outside_workspace",
    "parse_tcp_address",
    "sections",
]

S = TypeVar("S", bound=BaseModel)


class JsonFileSource(PydanticBaseSettingsSource):
    """Reads the optional JSON file at GLUE_APP_CONFIG_PATH (keys as in Appendix A)."""

    def get_field_value(self, field: Any, field_name: str) -> tuple[Any, str, bool]:
        return None, field_name, False

    def __call__(self) -> dict[str, Any]:
        path = os.environ.get("GLUE_APP_CONFIG_PATH")
        if not path:
            return {}
        try:
            data = json.loads(Path(path).read_text(encoding="utf-8"))
        except FileNotFoundError as exc:
            raise ConfigurationError(
                f"GLUE_APP_CONFIG_PATH names {path}, which does not exist"
            ) from exc
        except OSError as exc:
            raise ConfigurationError(f"config file {path} cannot be read: {exc}") from exc
        except json.JSONDecodeError as exc:
            raise ConfigurationError(f"config file {path} is not valid JSON: {exc}") from exc
        if not isinstance(data, dict):
            raise ConfigurationError(f"config file {path} must hold a JSON object of settings")
        return data


class Settings(
    WorkerSettings,
    SafetySettings,
    LogSettings,
    StorageSettings,
    WatchSettings,
    KpiSettings,
    RecordingSettings,
    BroadcastSettings,
    AccessSettings,
    HttpSettings,
    PlantSettings,
    OpcUaSettings,
    MqttSettings,
    SparkplugSettings,
    WebhookSettings,
    RobotSettings,
    CameraSettings,
    GlueSettings,
    QualitySettings,
    MotionSettings,
    RunEndSettings,
    CalibrationSettings,
    SimulationSettings,
    MaintenanceSettings,
    BaseSettings,
):
    """Every tunable of the cell server, with the specification's names: the sections,
    in the order docs/settings.md lists them, and the rules across them."""

    # allow_inf_nan=False: no setting is ever Infinity or NaN, from any source (an
    # infinite timeout disables its limit; an infinite cycle time made /kpis a 500).
    # Every number's lower bound is inclusive and what its meaning allows (a shift of
    # minutes, a timeout of milliseconds, a tolerance at a resolution a cell can measure),
    # never `> 0`: that let subnormals such as 3.55e-276 in (a zero-length KPI window, a
    # start failing at once). A bound of 0 is kept only where 0 means something (no
    # delay, every waypoint) and a subnormal means the same (tests/unit/test_config.py).
    # frozen=False: PATCH /settings and the marker teaching change settings in force;
    # the sections handed to components are frozen copies.
    model_config = SettingsConfigDict(
        env_prefix="GLUE_APP_",
        extra="forbid",
        populate_by_name=True,
        validate_default=True,
        allow_inf_nan=False,
        frozen=False,
    )

    def section(self, kind: type[S]) -> S:
        """This section's values in force now, as an instance of `kind` (frozen for a
        `Section`).

        Built from values already validated here, so without validating again; a
        component holding it sees a later PATCH /settings only by asking again.
        """
        values = {name: getattr(self, name) for name in kind.model_fields}
        return kind.model_construct(self.model_fields_set & values.keys(), **values)

    @model_validator(mode="after")
    def _pressure_inside_supervision(self) -> Settings:
        """Refuse supervision that would trip on the cell's own normal operation."""
        low, high = self.glue_pressure_range_psi
        if not low <= self.default_pressure_psi <= high:
            raise ValueError(
                f"default_pressure_psi ({self.default_pressure_psi:g}) must lie inside "
                f"glue_pressure_range_psi ({low:g}..{high:g}): every run would stop on it"
            )
        return self

    @model_validator(mode="after")
    def _marker_layout(self) -> Settings:
        """The marker layout is what the robot calibration maps to, so it is checked at load.

        Why each rule: a real table's layout is never the simulator's grid by accident (the
        default is refused for a real camera); a marker outside the workspace is one the robot
        could not be checked against; overlapping markers are a typo; and a homography needs
        four markers no three of which are on one line, also with any one marker left out,
        because the calibration's hold-out check fits the map without each marker in turn.
        """
        name = "marker_positions_mm"
        if not self.camera_simulated and name not in self.model_fields_set:
            raise ValueError(
                f"{name} must be set for a real camera (vision_camera_id="
                f"{self.vision_camera_id!r}): the default is the simulated table's grid, "
                "not your table's marker layout"
            )
        problems = marker_layout_problems(
            self.marker_positions_mm,
            self.workspace_min_mm,
            self.workspace_max_mm,
            self.marker_size_mm,
        )
        if problems:
            raise ValueError("; ".join(f"{name}: {problem}" for problem in problems))
        return self

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        return (init_settings, env_settings, JsonFileSource(settings_cls))

    def compatibility_notes(self) -> list[str]:
        """Specification keys that are accepted but cannot take effect here, and why.

        Why accepted at all: a configuration written for the original application
        (Appendix A) must load unchanged; refusing it would stop a cell at start-up
        over a key that changes nothing safety-relevant. Why said out loud: a
        technician who set one of them must not believe it is in force. The server
        logs each note at start-up (docs/operations-guide.md lists them).
        """
        notes = []
        if self.max_concurrent_operations != 1:
            notes.append(
                f"max_concurrent_operations={self.max_concurrent_operations} has no effect: "
                "the cell has one robot and one operational state at a time"
            )
        if not self.broadcast_enabled:
            notes.append(
                "broadcast_enabled=false has no effect: /ws is part of the HTTP API "
                "and needs a token like every other route (limit it with max_broadcast_clients)"
            )
        if "broadcast_port" in self.model_fields_set:
            notes.append(
                f"broadcast_port={self.broadcast_port} has no effect: /ws is served on the "
                "HTTP port (--port)"
            )
        if not self.analytics_enabled:
            notes.append(
                "analytics_enabled=false has no effect: the journal is what makes an "
                "acknowledged command durable, so it is always written"
            )
        if not self.performance_monitoring or "metrics_collection_interval" in (
            self.model_fields_set
        ):
            notes.append(
                "performance_monitoring and metrics_collection_interval have no effect: "
                "metrics are kept continuously and read on demand at GET /metrics"
            )
        return notes

    @property
    def log_file(self) -> Path:
        """Where the log file is (log_file_path, by default under the data directory)."""
        return self.data_file(self.log_file_path, "logs/glue_cell.log")


def sections() -> tuple[type[BaseModel], ...]:
    """The section classes `Settings` is made of, in its bases' order (the docs' order):
    every pydantic model among its bases, a `Section` or a plain BaseModel."""
    return tuple(
        base
        for base in Settings.__bases__
        if issubclass(base, BaseModel) and not issubclass(base, BaseSettings)
    )
