"""One Settings model for the whole server.

Values come, highest priority first, from: keyword arguments (tests and the
command line), `GLUE_APP_*` environment variables, the JSON file named by
`GLUE_APP_CONFIG_PATH`, then the defaults below. The keys are the
specification's (Appendix A) so a configuration written for the original
application keeps working; the hardware variables keep their original names
(`ROBOT_IP`, `VISION_CAMERA_ID`, `GLUE_CONTROLLER_PORT`) without the prefix.

A device address of `sim` means "start the simulator on loopback and talk to
it through the production client", so the default run exercises the same code
path as a real cell.
"""

from __future__ import annotations

import ipaddress
import itertools
import json
import math
import os
import re
import socket
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any, Literal
from urllib.parse import urlsplit

from pydantic import AliasChoices, Field, SecretStr, field_validator, model_validator
from pydantic_settings import (
    BaseSettings,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
)

from server.common.errors import ConfigurationError
from server.common.values import BYTE_SIZE_ACCEPTS, byte_size
from server.security import destinations
from server.settings.run_end import RunEndSettings
from server.settings.webhooks import WebhookTarget, named

SIMULATED = "sim"

# Coordinates and angles in the robot's base frame. Why these bounds: a cell's robot
# reaches a metre or two; ten metres is a typo caught, not a cell refused.
Millimetres = Annotated[float, Field(ge=-10_000, le=10_000)]
Degrees = Annotated[float, Field(ge=-360, le=360)]
Psi = Annotated[float, Field(ge=0, le=150)]  # the dispenser's pressure register's span
Celsius = Annotated[float, Field(ge=-40, le=150)]

# Robot positions (mm, robot base frame, on the table plane z=0) of ArUco markers 0-8.
DEFAULT_MARKER_POSITIONS_MM: list[tuple[float, float]] = [
    (x, y) for y in (-150.0, 0.0, 150.0) for x in (250.0, 400.0, 550.0)
]


def outside_workspace(
    point: Sequence[float], low: Sequence[float], high: Sequence[float]
) -> str | None:
    """Which axis of `point` (x, y, z mm; more is ignored) leaves [low, high], or None."""
    for axis, value, lo, hi in zip("xyz", point[:3], low, high, strict=True):
        if not lo <= value <= hi:
            return f"{axis}={value:.1f} mm, allowed {lo:.0f}..{hi:.0f} mm"
    return None


def parse_tcp_address(value: str) -> tuple[str, int]:
    """`tcp://host:port` → (host, port); ValueError naming the setting otherwise."""
    parts = urlsplit(value)
    try:
        port = parts.port
    except ValueError:  # past 65535
        port = None
    if parts.scheme != "tcp" or not parts.hostname or not port:
        raise ValueError(f"GLUE_CONTROLLER_PORT={value!r}: expected tcp://host:port")
    return parts.hostname, port


def marker_layout_problems(
    positions: Sequence[Sequence[float]],
    workspace_min: Sequence[float],
    workspace_max: Sequence[float],
    marker_size: float,
) -> list[str]:
    """Every way a marker layout fails (`Settings._marker_layout` says why each rule), each
    naming its markers: a taught draft is corrected in one pass, not one marker a try."""
    points = [(float(x), float(y)) for x, y in positions]
    (x_low, y_low, *_), (x_high, y_high, *_) = workspace_min, workspace_max
    problems = [
        f"marker {i} at ({x:g}, {y:g}) mm is outside the workspace (workspace_min_mm/"
        f"workspace_max_mm: x {x_low:g}..{x_high:g}, y {y_low:g}..{y_high:g} mm)"
        for i, (x, y) in enumerate(points)
        if not (x_low <= x <= x_high and y_low <= y <= y_high)
    ]
    diagonal = marker_size * math.sqrt(2.0)
    problems += [
        f"markers {i} and {j} are {math.dist(p, q):.1f} mm apart, less than a marker's "
        f"diagonal ({diagonal:.1f} mm for marker_size_mm={marker_size:g}): they would overlap"
        for (i, p), (j, q) in itertools.combinations(enumerate(points), 2)
        if math.dist(p, q) < diagonal
    ]
    for left_out in range(len(points)):
        rest = [p for i, p in enumerate(points) if i != left_out]
        if not _has_four_in_general_position(rest, marker_size):
            problems.append(
                f"the layout is degenerate: a calibration needs four markers no three of which "
                f"lie on one line (within marker_size_mm={marker_size:g} mm), also with any "
                f"one marker left out; without marker {left_out} there are not"
            )
            break
    return problems


def _has_four_in_general_position(points: list[tuple[float, float]], tolerance: float) -> bool:
    """Whether four of the points have no three within `tolerance` of one line."""

    def apart(a: tuple[float, float], b: tuple[float, float], c: tuple[float, float]) -> bool:
        cross = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
        longest = max(math.dist(a, b), math.dist(b, c), math.dist(a, c))
        return longest > 0 and abs(cross) / longest > tolerance  # the triangle's least height

    return any(
        all(apart(*three) for three in itertools.combinations(four, 3))
        for four in itertools.combinations(points, 4)
    )


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


# A cell id is one MQTT topic level and an OPC UA browse name: no '/', '+', '#', spaces.
CELL_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$"
# opc.tcp://host:port with an explicit port (a server must say where it listens).
OPCUA_ENDPOINT_PATTERN = r"^opc\.tcp://[A-Za-z0-9._:\[\]-]+:[0-9]{1,5}/?$"
MQTT_URL_PATTERN = r"^mqtts?://[^\s/:@]+(:[0-9]{1,5})?/?$"
# One or more topic levels: no wildcards, no empty level, no leading '$' (the broker's own).
MQTT_PREFIX_PATTERN = r"^[A-Za-z0-9._-]{1,64}(/[A-Za-z0-9._-]{1,64}){0,7}$"


def default_cell_id() -> str:
    """The host name, made a valid cell id (other characters become '-')."""
    name = re.sub(r"[^A-Za-z0-9._-]", "-", socket.gethostname()).strip("-.") or "cell"
    return name[:64] if name[0].isalnum() else f"cell-{name}"[:64]


class Settings(BaseSettings, RunEndSettings):
    """Every tunable of the cell server, with the specification's names."""

    # allow_inf_nan=False: no setting is ever Infinity or NaN, from any source (an
    # infinite timeout disables its limit; an infinite cycle time made /kpis a 500).
    # Every number's lower bound is inclusive and what its meaning allows (a shift of
    # minutes, a timeout of milliseconds, a tolerance at a resolution a cell can measure),
    # never `> 0`: that let subnormals such as 3.55e-276 in (a zero-length KPI window, a
    # start failing at once). A bound of 0 is kept only where 0 means something (no
    # delay, every waypoint) and a subnormal means the same (tests/unit/test_config.py).
    model_config = SettingsConfigDict(
        env_prefix="GLUE_APP_",
        extra="forbid",
        populate_by_name=True,
        validate_default=True,
        allow_inf_nan=False,
    )

    # Core state machine
    event_queue_size: int = Field(
        1000,
        ge=1,
        le=1_000_000,
        description="requests waiting for the worker; more are refused (503)",
    )
    processing_timeout: float = Field(
        60.0, ge=0.1, le=3600, description="seconds one attempt of an operation may run"
    )
    max_concurrent_operations: int = Field(
        1, ge=1, le=64, description="accepted for compatibility; the cell runs one at a time"
    )
    history_size: int = Field(1000, ge=10, le=1_000_000, description="transitions kept in memory")

    # Error handling
    error_recovery_attempts: int = Field(
        3, ge=0, le=100, description="retries of a recoverable fault, with auto_recovery_enabled"
    )
    error_recovery_delay: float = Field(
        2.0, ge=0, le=600, description="seconds before a retry, times the attempt's number"
    )
    auto_recovery_enabled: bool = Field(
        False, description="retry an operation that failed on a recoverable fault"
    )

    # Performance monitoring
    performance_monitoring: bool = Field(
        True, description="accepted, no effect: metrics are always kept (GET /metrics)"
    )
    metrics_collection_interval: float = Field(
        10.0, ge=0.1, le=3600, description="seconds; accepted, no effect (metrics read on demand)"
    )
    performance_history_size: int = Field(
        1000, ge=10, le=1_000_000, description="processing-time samples kept for statistics"
    )

    # Logging
    logging_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = Field(
        "INFO",
        validation_alias=AliasChoices("logging_level", "GLUE_APP_LOG_LEVEL"),
        description="least severity logged, on the console and in the log file",
    )
    log_file_path: str | None = Field(None, description="default <data>/logs/glue_cell.log")
    log_rotation_size: str = Field(
        "10MB",
        description="the log file is rotated at this size (a number and KB, MB or GB)",
        json_schema_extra={"accepts": f"{BYTE_SIZE_ACCEPTS}, at least 1KB"},
    )
    log_retention_days: int = Field(30, ge=1, le=3650, description="days rotated logs are kept")

    # Persistence
    data_path: Path = Field(Path("data"), description="where state, journal and tokens live")
    state_persistence: bool = Field(
        True, description="save the state snapshot, to tell an interrupted run after a restart"
    )
    persistence_file: str | None = Field(None, description="default <data>/state.json")
    persistence_interval: float = Field(
        30.0, ge=1, le=3600, description="seconds between saves of the state snapshot"
    )

    # Broadcasting (/ws is always served on the HTTP port, whatever broadcast_port says)
    broadcast_enabled: bool = Field(True, description="accepted, no effect: /ws is always served")
    broadcast_port: int = Field(
        8000, ge=1, le=65535, description="accepted, no effect: /ws is on the HTTP port (--port)"
    )
    max_broadcast_clients: int = Field(
        100, ge=1, le=100_000, description="live views (/ws) open at once, all tokens together"
    )
    max_broadcast_clients_per_token: int = Field(
        10,
        ge=1,
        le=100_000,
        description="live views (/ws) one token may hold open at once, so one token "
        "cannot take every slot",
    )
    broadcast_clients_reserved: int = Field(
        2,
        ge=0,
        le=100_000,
        description="of max_broadcast_clients, the slots only maintenance and admin may "
        "use (at most all but one)",
    )
    ws_client_buffer: int = Field(256, ge=8, le=100_000, description="messages queued per client")
    ws_ping_interval: float = Field(
        20.0, ge=1, le=600, description="seconds between pings of a /ws client; as long to answer"
    )

    # Analytics and the journal
    analytics_enabled: bool = Field(
        True, description="accepted, no effect: the journal is always written"
    )
    analytics_database: str | None = Field(None, description="default <data>/journal.db")
    analytics_retention_days: int = Field(
        90, ge=1, le=3650, description="days of journal rows kept"
    )
    journal_synchronous: Literal["OFF", "NORMAL", "FULL"] = Field(
        "FULL", description="SQLite synchronous level: FULL survives power loss"
    )
    shift_hours: float = Field(
        8.0, ge=0.25, le=24 * 31, description="hours of the default KPI window"
    )
    design_cycle_time_s: float = Field(
        30.0, ge=0.1, le=3600, description="ideal time of one trajectory run, for OEE performance"
    )

    # Access
    trusted_networks: list[str] = Field(
        default_factory=list, description="if set, only clients from these networks (CIDR)"
    )
    trusted_proxies: list[str] = Field(
        default_factory=list,
        max_length=256,
        description="proxies (CIDR or address) whose forwarded_header is believed; none by "
        "default: the client is the peer, whatever a request's headers say",
    )
    forwarded_header: Literal["x-forwarded-for", "forwarded"] = Field(
        "x-forwarded-for",
        description="the header the trusted_proxies set (X-Forwarded-For or RFC 7239 "
        "Forwarded); the other one is never read",
    )
    cors_allowed_origins: list[str] = Field(default_factory=list, description="closed if empty")
    max_request_bytes: int = Field(
        1024 * 1024, ge=1024, le=64 * 1024 * 1024, description="largest request body, bytes"
    )

    # HTTPS: off unless both files are set (docs/security.md, "TLS")
    tls_cert_file: Path | None = Field(
        None,
        description="the server's certificate (PEM, its chain after it): with tls_key_file, "
        "the HTTP port serves https and wss only (TLS 1.2 or later)",
    )
    tls_key_file: Path | None = Field(
        None,
        description="the private key (PEM, not encrypted) of tls_cert_file; readable by the "
        "server's user only",
    )

    # Guessing and slow clients (docs/security.md, "Guessing and slow clients")
    auth_failure_limit: int = Field(
        20,
        ge=1,
        le=10_000,
        description="bad tokens or tickets from one address within auth_failure_window "
        "that lock it out (429 with Retry-After; never the e-stop)",
    )
    auth_failure_window: float = Field(
        60.0, ge=1, le=86_400, description="seconds over which auth_failure_limit is counted"
    )
    auth_lockout_s: float = Field(
        60.0, ge=1, le=86_400, description="seconds a locked-out address is answered 429"
    )
    audit_repeat_window: float = Field(
        60.0,
        ge=1,
        le=3600,
        description="seconds within which identical refusals (same who, address, action, "
        "outcome and reason) are one audit row with a count",
    )
    http_header_timeout: float = Field(
        10.0,
        ge=0.5,
        le=300,
        description="seconds a connection has to send a request's headers (from its first "
        "byte, or from connecting); then it is closed",
    )
    http_keepalive_timeout: float = Field(
        5.0, ge=0.5, le=3600, description="seconds an idle keep-alive connection stays open"
    )
    http_max_connections: int = Field(
        512,
        ge=16,
        le=100_000,
        description="open HTTP and WebSocket connections in all; at the limit the oldest one "
        "still waiting for its headers is closed for a new one",
    )
    http_max_connections_per_address: int = Field(
        64,
        ge=1,
        le=100_000,
        description="open HTTP connections from one address (not a trusted proxy), used up "
        "to http_max_connections",
    )

    # The plant's interfaces (docs/plant-integration.md)
    cell_id: str = Field(
        default_factory=lambda: default_cell_id(),
        pattern=CELL_ID_PATTERN,
        description="names this cell to the plant: its OPC UA object and its MQTT topics "
        "(glue/<cell_id>/...)",
        json_schema_extra={
            "default_text": "the host name",
            "accepts": "letters, digits, '.', '_' and '-', 1 to 64, the first a letter or digit",
        },
    )
    opcua_endpoint: str | None = Field(
        None,
        pattern=OPCUA_ENDPOINT_PATTERN,
        description="serve OPC UA (PackML tags, methods) at this endpoint, e.g. "
        "opc.tcp://0.0.0.0:4840; off if unset",
        json_schema_extra={"accepts": "opc.tcp://HOST:PORT (PORT 1 to 65535), or unset"},
    )
    opcua_allow_unsecured: bool = Field(
        True,
        description="also offer OPC UA security policy None (a lab); Basic256Sha256 Sign and "
        "SignAndEncrypt are always offered",
    )
    opcua_admin_interval: float = Field(
        5.0,
        ge=1,
        le=3600,
        description="seconds between refreshes of the OPC UA Admin figures (KPIs of the shift)",
    )
    plant_progress_interval: float = Field(
        0.25,
        ge=0,
        le=10,
        description="a run's progress reaches the plant (OPC UA CellState, MQTT progress) at "
        "most this often, in seconds, the latest kept; transitions are never held and a "
        "run's final progress goes before the transition that ends it; 0: every waypoint",
    )

    # MQTT (docs/plant-integration.md): off unless mqtt_url is set
    mqtt_url: str | None = Field(
        None,
        pattern=MQTT_URL_PATTERN,
        description="the plant's MQTT broker, mqtt://host:1883 or mqtts://host:8883; "
        "off when unset",
        json_schema_extra={"accepts": "mqtt://host[:port] or mqtts://host[:port]"},
    )
    mqtt_ca_file: Path | None = Field(
        None, description="CA certificate (PEM) the broker's is checked against (mqtts://)"
    )
    mqtt_username: str | None = Field(
        None, max_length=256, description="user name at the broker, if it asks for one"
    )
    mqtt_password: SecretStr | None = Field(
        None,
        description="password at the broker; never logged, shown as ********** by GET /settings",
    )
    mqtt_topic_prefix: str = Field(
        "glue",
        pattern=MQTT_PREFIX_PATTERN,
        description="first topic level(s): <prefix>/<cell_id>/state and the like",
        json_schema_extra={"accepts": "topic levels of letters, digits, '.', '_', '-', '/'"},
    )
    mqtt_keepalive: int = Field(
        30,
        ge=1,
        le=3600,
        description="seconds of MQTT keep-alive: the broker publishes the last will "
        "(status offline) after 1.5 times this without a word from the cell",
    )
    mqtt_buffer: int = Field(
        1000,
        ge=1,
        le=1_000_000,
        description="event, progress and alert messages kept while the broker is away; the "
        "oldest are dropped beyond it (counted in /health); retained topics keep their latest",
    )
    mqtt_reconnect_max: float = Field(
        30.0,
        ge=0.1,
        le=600,
        description="longest wait between reconnection attempts, seconds (from 0.1 s, doubling)",
    )
    mqtt_kpis_interval: float = Field(
        10.0, ge=1, le=3600, description="seconds between publications of the retained KPIs"
    )
    mqtt_health_interval: float = Field(
        10.0,
        ge=1,
        le=3600,
        description="seconds between publications of the retained health (also on a change)",
    )
    mqtt_commands: bool = Field(
        False,
        description="accept commands on <prefix>/<cell_id>/command/<name>, each signed with "
        "a token (same roles as HTTP); off by default",
    )
    mqtt_command_max_age: float = Field(
        30.0,
        ge=1,
        le=600,
        description="seconds a signed MQTT command stays valid after its ts_ms; an older one "
        "is refused as stale (and its nonce need only be remembered this long)",
    )
    mqtt_command_max_skew: float = Field(
        5.0,
        ge=0,
        le=60,
        description="seconds a signed MQTT command's ts_ms may be ahead of the cell's clock "
        "(the sender's clock running fast); further ahead is refused",
    )

    # Notifications (webhooks; docs/plant-integration.md)
    webhooks: list[WebhookTarget] = Field(
        default_factory=list,
        max_length=32,
        description="where the cell POSTs a signed JSON notice of a fault, an alert, a state "
        "change or a completed run: a JSON list of {name, url, events, secret or "
        "secret_file}; none by default",
        json_schema_extra={
            "accepts": 'a JSON list of objects such as {"url": "https://host/hook", '
            '"events": ["fault", "run_completed"], "secret_file": "/run/secrets/hook"} '
            "(events: fault, alert, state, run_completed; default all; a secret of at "
            "least 16 characters, inline or in a file)",
            "holds_secrets": True,
        },
    )
    webhook_allowed_networks: list[str] = Field(
        default_factory=list,
        max_length=256,
        description="networks (CIDR or address) a webhook may post to although the "
        "destination policy refuses them: loopback, link-local, unspecified and this host's "
        "own addresses are refused, at load and at each connection (docs/security.md); "
        "none by default",
    )
    webhook_queue_size: int = Field(
        100,
        ge=1,
        le=100_000,
        description="notices waiting per webhook; when full, the oldest is dropped "
        "(counted at GET /webhooks and journaled)",
    )
    webhook_timeout: float = Field(
        5.0, ge=0.1, le=120, description="seconds one delivery attempt may take (connect to answer)"
    )
    webhook_max_attempts: int = Field(
        5,
        ge=1,
        le=50,
        description="attempts per notice: a timeout, a connection error, 408, 429 or 5xx is "
        "retried; any other answer is final",
    )
    webhook_retry_delay: float = Field(
        1.0, ge=0.01, le=600, description="seconds before the first retry; doubled for each next"
    )
    webhook_retry_max_delay: float = Field(
        60.0,
        ge=0.01,
        le=3600,
        description="the longest wait between two attempts (a Retry-After included)",
    )

    # Hardware timeouts (seconds)
    robot_communication_timeout: float = Field(
        10.0, ge=0.1, le=300, description="seconds for the robot controller to answer a request"
    )
    vision_processing_timeout: float = Field(
        5.0, ge=0.1, le=300, description="seconds for the camera to deliver a frame"
    )
    camera_preview_fps: float = Field(
        5.0,
        ge=0.5,
        le=15,
        description="the camera set-up view (/camera/preview/ws) sends at most this many "
        "annotated frames a second, whatever the number of clients; each costs a capture, "
        "a marker detection and a JPEG, off the event loop",
    )
    camera_preview_clients: int = Field(
        2,
        ge=1,
        le=10,
        description="at most this many clients watch the camera set-up view at once; one "
        "more is refused",
    )
    glue_system_timeout: float = Field(
        15.0, ge=0.1, le=300, description="seconds for the glue dispenser to answer"
    )

    # Safety (seconds)
    emergency_stop_timeout: float = Field(
        1.0, ge=0.05, le=10, description="seconds each device command of a software stop may take"
    )
    pause_hold_timeout: float = Field(
        2.0,
        ge=0.05,
        le=60,
        description="a pause must have the valve closed and the robot confirmed still "
        "within this; otherwise it is refused and the cell goes to ERROR (PAUSE_NOT_HELD)",
    )
    safe_position_timeout: float = Field(
        30.0, ge=0.1, le=600, description="seconds the move to the safe position may take"
    )
    planning_timeout: float = Field(
        10.0,
        ge=0.01,
        le=600,
        description="seconds a run may spend planning its path (PLANNING_TIMEOUT past it)",
    )
    error_state_timeout: float = Field(
        300.0, ge=1, le=86_400, description="seconds in ERROR before an alert is raised"
    )
    reset_probe_timeout: float = Field(
        2.0,
        ge=0.01,
        le=60,
        description="seconds a reset waits for every device's live answer (all at once); "
        "a device not answering in time refuses the reset, and the cell keeps taking "
        "e-stops and faults meanwhile",
    )

    # Hardware addresses: "sim" starts the simulator on loopback.
    robot_ip: str = Field(
        SIMULATED,
        validation_alias=AliasChoices("robot_ip", "ROBOT_IP"),
        description="the robot controller's address (JSON-RPC over TCP); sim: the simulator",
    )
    robot_port: int = Field(
        30003, ge=0, le=65535, description="the robot controller's TCP port (0: any, simulator)"
    )
    robot_heartbeat_interval: float = Field(
        1.0,
        ge=0.05,
        le=60,
        description="a robot link quiet this long is asked for the position; no answer "
        "within robot_communication_timeout is a fault, in IDLE too",
    )
    vision_camera_id: str = Field(
        SIMULATED,
        validation_alias=AliasChoices("vision_camera_id", "VISION_CAMERA_ID"),
        description="the camera: an OpenCV index or URL; sim: the simulated camera",
    )
    glue_controller_port: str = Field(
        SIMULATED,
        validation_alias=AliasChoices("glue_controller_port", "GLUE_CONTROLLER_PORT"),
        description="the dispenser's serial port (Modbus RTU) or tcp://host:port; sim: simulator",
    )
    glue_modbus_device_id: int = Field(1, ge=1, le=247, description="the dispenser's Modbus unit")
    # Glue supervision (docs/hardware.md says where each default comes from)
    glue_pressure_range_psi: tuple[Psi, Psi] = Field(
        (20.0, 60.0),
        description="measured glue pressure above high PSI is a fault at any time, below low "
        "PSI while the valve is open (the dispenser's own alarms apply too); default: the "
        "default setpoint (default_pressure_psi, 40 PSI) +-50 %",
    )
    glue_flow_deviation_pct: float = Field(
        20.0,
        ge=1,
        le=100,
        description="while spraying, measured flow off its setpoint by more than this many "
        "percent for glue_flow_deviation_s is a fault",
    )
    glue_flow_deviation_s: float = Field(
        0.5,
        ge=0.05,
        le=10,
        description="how long a flow deviation may last (the valve's opening transient is "
        "shorter); 0.5 s is 50 mm of bead at the default spray speed",
    )
    glue_temperature_range_c: tuple[Celsius, Celsius] = Field(
        (10.0, 40.0),
        description="glue temperature outside [low, high] degC is a fault at any time; the "
        "default suits a room-temperature adhesive, set it for a heated one",
    )
    glue_link_timeout: float = Field(
        0.5,
        ge=0.05,
        le=5,
        description="a dispenser silent this long while its valve may be open is a fault at "
        "once (the valve could not be confirmed closed); must exceed glue_poll_interval",
    )
    glue_poll_interval: float = Field(
        0.1,
        ge=0.02,
        le=1,
        description="how often the dispenser's status is read (valve, flow, pressure, "
        "temperature, alarms)",
    )
    device_push_interval: float = Field(
        0.1,
        ge=0.02,
        le=1,
        description="while an operation runs, a `device` message (valve, flow, pressure, "
        "robot position) is pushed on /ws at most this often; once a second otherwise",
    )

    # Quality: each part inspected, production orders (docs/quality.md)
    inspection_enabled: bool = Field(
        True,
        description="after each completed spray run, measure the run and inspect the part's "
        "bead (GET /runs/{id}/inspection); off: runs are neither judged nor counted as parts",
    )
    quality_sample_interval_s: float = Field(
        0.05,
        ge=0.01,
        le=1,
        description="while spraying, the robot's position and the dispenser's flow are read "
        "this often for the run's trajectory precision and dispensing consistency",
    )
    trajectory_precision_limit_mm: float = Field(
        1.0,
        ge=0.01,
        le=50,
        description="a part is defective when the robot strayed further than this (mm) from "
        "a spray segment",
    )
    dispensing_flow_tolerance_percent: float = Field(
        10.0,
        ge=0.1,
        le=100,
        description="flow further than this (%) from its setpoint counts as out of tolerance",
    )
    dispensing_max_out_of_tolerance_s: float = Field(
        0.5,
        ge=0,
        le=60,
        description="a part is defective when its flow was out of tolerance longer than this "
        "(s) while spraying",
    )
    glue_volume_tolerance_percent: float = Field(
        20.0,
        ge=0.1,
        le=100,
        description="a part is defective when the glue dispensed differs from what its path "
        "needs (flow setpoint × length / speed) by more than this (%): wider than the flow's "
        "tolerance, as the arm stands still a few ms at each waypoint with the valve open",
    )
    bead_width_tolerance_percent: float = Field(
        30.0,
        ge=0.1,
        le=100,
        description="a bead narrower or wider than expected (from flow over speed) by more "
        "than this (%) is a defect",
    )
    bead_max_gap_mm: float = Field(
        3.0, ge=0.1, le=100, description="longest stretch of a spray segment without bead (mm)"
    )
    bead_max_offset_mm: float = Field(
        1.5,
        ge=0.1,
        le=50,
        description="furthest the bead's centre may lie from its planned path on the part (mm)",
    )
    order_defect_limit: int = Field(
        3,
        ge=1,
        le=1000,
        description="defective parts in a row that stop an order and the cell: a nozzle or "
        "a calibration is wrong, and more parts would be scrap",
    )

    # Cell geometry and motion
    safe_position: tuple[Millimetres, Millimetres, Millimetres, Degrees, Degrees, Degrees] = Field(
        (400.0, 0.0, 200.0, 180.0, 0.0, 0.0),
        description="where `home` sends the robot: x, y, z mm (inside the workspace) and rx, "
        "ry, rz degrees",
    )
    spray_height_mm: float = Field(20.0, ge=0, le=500, description="nozzle height over the part")
    travel_speed_mm_s: float = Field(250.0, ge=1, le=2000, description="mm/s between beads")
    spray_speed_mm_s: float = Field(100.0, ge=1, le=2000, description="mm/s along a bead")
    acceleration_mm_s2: float = Field(1000.0, ge=10, le=20000, description="mm/s² of every move")
    default_flow_rate_ml_min: float = Field(
        30.0,
        ge=0,
        le=1000,
        description="ml/min; accepted, no effect: each workpiece's spray settings set the flow",
    )
    default_pressure_psi: float = Field(
        40.0,
        ge=0,
        le=150,
        description="PSI pressure setpoint of every run; inside glue_pressure_range_psi",
    )
    workspace_min_mm: tuple[Millimetres, Millimetres, Millimetres] = Field(
        (100.0, -400.0, -5.0),
        description="x, y, z mm: no move goes below these; each below workspace_max_mm",
    )
    workspace_max_mm: tuple[Millimetres, Millimetres, Millimetres] = Field(
        (800.0, 400.0, 500.0), description="x, y, z mm: no move goes above these"
    )
    jog_max_step_mm: float = Field(
        50.0,
        ge=0.1,
        le=200,
        description="the longest step one jog may ask for along its axis (maintenance "
        "teaching marker positions); a longer one is refused before anything moves",
    )
    jog_speed_mm_s: float = Field(
        20.0,
        ge=1,
        le=250,
        description="speed of a jog: slow, so a person beside the table can follow the arm",
    )
    marker_positions_mm: list[tuple[Millimetres, Millimetres]] = Field(
        default_factory=lambda: list(DEFAULT_MARKER_POSITIONS_MM),
        description="robot (x, y) mm on the table of the centres of ArUco markers 0-8; "
        "the default is the simulated table's grid, so a real camera needs it set",
    )
    marker_size_mm: float = Field(
        30.0,
        ge=1,
        le=500,
        description="side of each marker's black square as printed (measure it): the "
        "robot calibration checks its map's scale against it",
    )
    calibration_max_error_mm: float = Field(
        1.0, ge=0.01, le=20, description="robot calibration fails above this mean marker error (mm)"
    )
    calibration_max_scale_error_pct: float = Field(
        1.0,
        ge=0.01,
        le=10,
        description="robot calibration fails when the markers' side through its map differs "
        "from marker_size_mm by more than this (%)",
    )
    calibration_max_holdout_error_mm: float = Field(
        1.0,
        ge=0.01,
        le=20,
        description="robot calibration fails when a map fitted without one marker misses "
        "that marker by more than this (leave-one-out, worst marker)",
    )
    chessboard_cols: int = Field(9, ge=3, le=40, description="inner corners per row")
    chessboard_rows: int = Field(6, ge=3, le=40, description="inner corners per column")
    chessboard_square_mm: float = Field(
        30.0, ge=1, le=500, description="side of one chessboard square as printed"
    )
    camera_calibration_views: int = Field(
        10, ge=5, le=100, description="chessboard views a camera calibration takes"
    )
    camera_calibration_view_interval_s: float | None = Field(
        None,
        ge=0,
        le=60,
        description="pause between chessboard captures, for a person to move the board; "
        "default 2 s on a real camera, 0 on the simulator (it shows its own views)",
    )
    commission_simulated_cell: bool = Field(
        True, description="calibrate a fresh simulated cell and put its demo part in the library"
    )
    simulation_speed_factor: float = Field(
        1.0, ge=0.1, le=1000, description="simulated devices run this many times faster"
    )

    @field_validator("trusted_proxies")
    @classmethod
    def _proxy_networks(cls, value: list[str]) -> list[str]:
        """A typo here would silently trust nobody (or the wrong host): refuse it at load."""
        for entry in value:
            try:
                ipaddress.ip_network(entry.strip(), strict=False)
            except ValueError:
                raise ValueError(
                    f"trusted_proxies: {entry!r} is not an IP address or network (CIDR)"
                ) from None
        return value

    @field_validator("opcua_endpoint")
    @classmethod
    def _opcua_port(cls, value: str | None) -> str | None:
        """The pattern takes five digits; a port past 65535 is refused here, at load."""
        if value is not None and not 1 <= int(value.rstrip("/").rsplit(":", 1)[1]) <= 65535:
            raise ValueError("the OPC UA endpoint's port must be 1 to 65535")
        return value

    @field_validator("mqtt_url")
    @classmethod
    def _mqtt_port(cls, value: str | None) -> str | None:
        """The pattern takes five digits: 99999 crashed the start, 0 meant 1883 silently."""
        try:
            port = urlsplit(value).port if value else None
        except ValueError:  # past 65535
            port = 0
        if port is not None and not 1 <= port <= 65535:
            raise ValueError("the broker's port must be 1 to 65535")
        return value

    @field_validator("glue_controller_port")
    @classmethod
    def _glue_tcp_port(cls, value: str) -> str:
        """tcp://host:port (the network simulator, a serial server): checked at load, where a
        port past 65535 crashed the start and a missing one failed at the first connect."""
        if value.startswith("tcp://"):
            try:
                parse_tcp_address(value)
            except ValueError:
                raise ValueError("a TCP dispenser is tcp://HOST:PORT, PORT 1 to 65535") from None
        return value

    @field_validator("webhooks")
    @classmethod
    def _webhooks_named(cls, value: list[WebhookTarget]) -> list[WebhookTarget]:
        return named(value)

    @field_validator("webhook_allowed_networks")
    @classmethod
    def _webhook_networks(cls, value: list[str]) -> list[str]:
        destinations.parse_networks(value)  # a typo refused at load, naming the entry
        return value

    @model_validator(mode="after")
    def _webhook_destinations(self) -> Settings:
        """A webhook to the cell itself, loopback or link-local is refused at load, naming the
        webhook (never its path or query): the cell must not be made to post to itself."""
        allowed = destinations.parse_networks(self.webhook_allowed_networks)
        for target in self.webhooks:
            host = urlsplit(target.url).hostname or ""
            why = destinations.load_refusal(host, allowed)
            if why is not None:
                raise ValueError(
                    f"webhook {target.name!r} posts to {host}, {why}: refused by the webhook "
                    f"destination policy (add its network to {destinations.SETTING} to "
                    "allow it)"
                )
        return self

    @field_validator("glue_pressure_range_psi")
    @classmethod
    def _ordered_range(cls, value: tuple[float, float]) -> tuple[float, float]:
        low, high = value
        if not 0 <= low < high <= 150:
            raise ValueError("glue_pressure_range_psi needs 0 <= low < high <= 150 PSI")
        return value

    @field_validator("glue_temperature_range_c")
    @classmethod
    def _ordered_temperatures(cls, value: tuple[float, float]) -> tuple[float, float]:
        low, high = value
        if not -40 <= low < high <= 150:
            raise ValueError("glue_temperature_range_c needs -40 <= low < high <= 150 degC")
        return value

    @model_validator(mode="after")
    def _consistent_glue_supervision(self) -> Settings:
        """Refuse supervision that would trip on the cell's own normal operation."""
        low, high = self.glue_pressure_range_psi
        if not low <= self.default_pressure_psi <= high:
            raise ValueError(
                f"default_pressure_psi ({self.default_pressure_psi:g}) must lie inside "
                f"glue_pressure_range_psi ({low:g}..{high:g}): every run would stop on it"
            )
        if self.glue_link_timeout <= self.glue_poll_interval:
            raise ValueError(
                f"glue_link_timeout ({self.glue_link_timeout:g} s) must exceed "
                f"glue_poll_interval ({self.glue_poll_interval:g} s)"
            )
        return self

    @field_validator("log_rotation_size")
    @classmethod
    def _a_log_size(cls, value: str) -> str:
        """Checked here, with the other settings: the log's set-up reads it before the cell
        starts, and a bad size there was a traceback instead of one line."""
        if byte_size(value) < 1024:
            raise ValueError(f"{value!r} is below 1KB")
        return value

    @field_validator("marker_positions_mm")
    @classmethod
    def _nine_markers(cls, value: list[tuple[float, float]]) -> list[tuple[float, float]]:
        if len(value) != 9:
            raise ValueError("marker_positions_mm needs the robot positions of markers 0-8 (nine)")
        return value

    @model_validator(mode="after")
    def _tls_pair(self) -> Settings:
        """A certificate without its key (or the reverse) cannot serve https, and serving
        plain http instead would send the tokens in clear that the setting was meant to
        protect: refused at load. The files themselves are read at start
        (server/bootstrap/tls.py)."""
        if (self.tls_cert_file is None) != (self.tls_key_file is None):
            missing = "tls_key_file" if self.tls_key_file is None else "tls_cert_file"
            raise ValueError(f"tls_cert_file and tls_key_file go together: {missing} is not set")
        return self

    @model_validator(mode="after")
    def _workspace_ordered(self) -> Settings:
        """An empty workspace would refuse every move with a message about the move."""
        for axis, low, high in zip(
            "xyz", self.workspace_min_mm, self.workspace_max_mm, strict=True
        ):
            if not low < high:
                raise ValueError(
                    f"workspace_min_mm must be below workspace_max_mm on every axis; "
                    f"{axis}: {low:g} is not below {high:g}"
                )
        return self

    @model_validator(mode="after")
    def _safe_position_inside(self) -> Settings:
        """Every run's first move and `home` go to the safe position: outside the workspace,
        `home` was refused and every run accepted, then failed with WORKSPACE_VIOLATION."""
        problem = outside_workspace(
            self.safe_position, self.workspace_min_mm, self.workspace_max_mm
        )
        if problem is not None:
            raise ValueError(
                f"safe_position is outside the workspace ({problem}; workspace_min_mm, "
                "workspace_max_mm)"
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
    def robot_simulated(self) -> bool:
        return self.robot_ip == SIMULATED

    @property
    def glue_simulated(self) -> bool:
        return self.glue_controller_port == SIMULATED

    @property
    def camera_simulated(self) -> bool:
        return self.vision_camera_id == SIMULATED

    def data_file(self, configured: str | None, default: str) -> Path:
        """A file under the data directory unless configured as an absolute path."""
        path = Path(configured) if configured else Path(default)
        return path if path.is_absolute() else self.data_path / path
