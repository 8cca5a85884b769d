"""gluectl's global options (--url, --token, --json, --mqtt, ...): read and checked once,
before any command runs, into the `Options` every command is given through typer's
context. A wrong value is a usage error here, not a failure later.
"""

from __future__ import annotations

import ssl
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Annotated

import httpx
import typer

from clients.client import (
    CA_FILE_ENV,
    DATA_DIR_ENV,
    DEFAULT_URL,
    TOKEN_ENV,
    URL_ENV,
    AsyncCellClient,
    CellClient,
    normalize_url,
    resolve_token,
    trust,
)
from clients.client.mqtt_commands import MqttCellClient, MqttTarget
from clients.gluectl.exit_codes import EXIT_OK
from clients.line_model import DEFAULT_PREFIX


@dataclass(frozen=True)
class Options:
    """The global options, resolved once in the callback."""

    url: str
    token: str | None
    token_source: str
    json: bool
    timeout: float
    mqtt: MqttTarget | None = None  # commands go over this broker instead of HTTP
    ca_file: Path | None = None

    def client(self) -> CellClient:
        return CellClient(self.url, self.token, timeout=self.timeout, ca_file=self.ca_file)

    def command_client(self) -> CellClient | MqttCellClient:
        """Where commands go: the broker with --mqtt, else the HTTP API."""
        if self.mqtt is not None:
            return MqttCellClient(self.mqtt, self.token, timeout=self.timeout)
        return self.client()

    def async_client(self) -> AsyncCellClient:
        return AsyncCellClient(self.url, self.token, timeout=self.timeout, ca_file=self.ca_file)


JsonFlag = Annotated[
    bool, typer.Option("--json", help="Machine-readable output (same as the global --json).")
]


def package_version() -> str:
    """The installed distribution's version (pyproject.toml), or why it is unknown."""
    try:
        return metadata.version("glue-cell-server")
    except metadata.PackageNotFoundError:
        return "(not installed: run from a checkout)"


def _show_version(value: bool) -> None:
    if value:
        typer.echo(f"gluectl {package_version()}")
        raise typer.Exit(EXIT_OK)


def main_options(
    ctx: typer.Context,
    url: Annotated[
        str, typer.Option("--url", envvar=URL_ENV, help="The cell server's base URL.")
    ] = DEFAULT_URL,
    token: Annotated[
        str | None,
        typer.Option(
            "--token",
            envvar=TOKEN_ENV,
            help="Bearer token; default: the data dir's admin.token.",
            show_default=False,
        ),
    ] = None,
    data_dir: Annotated[
        Path | None,
        typer.Option(
            "--data-dir",
            help=f"Where to find admin.token (default: ${DATA_DIR_ENV}, else ./data).",
            show_default=False,
        ),
    ] = None,
    ca_file: Annotated[
        Path | None,
        typer.Option(
            "--ca-file",
            envvar=CA_FILE_ENV,
            help="CA certificate (PEM) an https server's certificate must chain to "
            "(default: the public CAs).",
            show_default=False,
        ),
    ] = None,
    json_output: Annotated[
        bool, typer.Option("--json", help="Machine-readable output: one JSON document.")
    ] = False,
    timeout: Annotated[
        float, typer.Option("--http-timeout", min=0.1, help="Seconds to wait for each answer.")
    ] = 10.0,
    version: Annotated[
        bool,
        typer.Option(
            "--version", is_eager=True, callback=_show_version, help="Print the version and exit."
        ),
    ] = False,
    mqtt: Annotated[
        str | None,
        typer.Option(
            "--mqtt",
            envvar="GLUE_MQTT_URL",
            help="Send commands over this broker (mqtt://host:1883, mqtts://host:8883), signed.",
            show_default=False,
        ),
    ] = None,
    cell_id: Annotated[
        str | None,
        typer.Option(
            "--cell-id",
            envvar="GLUE_CELL_ID",
            help="The cell to command (--mqtt).",
            show_default=False,
        ),
    ] = None,
    mqtt_user: Annotated[
        str | None,
        typer.Option("--mqtt-user", envvar="GLUE_MQTT_USER", help="User name at the broker."),
    ] = None,
    mqtt_password: Annotated[
        str | None,
        typer.Option(
            "--mqtt-password",
            envvar="GLUE_MQTT_PASSWORD",
            help="Password at the broker (better: the env var or --mqtt-password-file).",
            show_default=False,
        ),
    ] = None,
    mqtt_password_file: Annotated[
        Path | None,
        typer.Option("--mqtt-password-file", help="A file whose first line is the password."),
    ] = None,
    mqtt_ca_file: Annotated[
        Path | None,
        typer.Option("--mqtt-ca-file", help="CA certificate (PEM) for an mqtts:// broker."),
    ] = None,
    mqtt_prefix: Annotated[
        str, typer.Option("--mqtt-prefix", help="The cell's topic prefix.")
    ] = DEFAULT_PREFIX,
) -> None:
    """Drive and watch the glue cell over its HTTP and WebSocket API."""
    try:
        url = str(httpx.URL(normalize_url(url)))
    except httpx.InvalidURL as exc:
        raise typer.BadParameter(str(exc), param_hint="--url") from None
    if ca_file is not None:  # read now: a wrong path is a usage error, not "unreachable"
        try:
            trust(ca_file)
        except (OSError, ssl.SSLError) as exc:
            reason = getattr(exc, "strerror", None) or str(exc)
            raise typer.BadParameter(f"{ca_file}: {reason}", param_hint="--ca-file") from None
    resolved = resolve_token(token, data_dir=data_dir)
    where = data_dir or f"${DATA_DIR_ENV} or ./data"
    if token:
        source = f"from --token or ${TOKEN_ENV}"
    elif resolved:
        source = f"from admin.token in {where}"
    else:
        source = f"none found (--token, ${TOKEN_ENV}, or admin.token in {where})"
    target = None
    if mqtt:
        target = _mqtt_target(
            mqtt, cell_id, mqtt_user, mqtt_password, mqtt_password_file, mqtt_ca_file, mqtt_prefix
        )
    ctx.obj = Options(url, resolved, source, json_output, timeout, target, ca_file)


def _mqtt_target(
    url: str,
    cell_id: str | None,
    user: str | None,
    password: str | None,
    password_file: Path | None,
    ca_file: Path | None,
    prefix: str,
) -> MqttTarget:
    """The broker and cell of --mqtt, checked before anything is sent."""
    if not cell_id:
        raise typer.BadParameter(
            "--mqtt needs --cell-id (or $GLUE_CELL_ID)", param_hint="--cell-id"
        )
    if password_file is not None:
        try:
            lines = password_file.read_text(encoding="utf-8").splitlines()
        except OSError as error:
            raise typer.BadParameter(str(error), param_hint="--mqtt-password-file") from None
        password = lines[0] if lines else ""
    target = MqttTarget(url, cell_id, prefix, user, password, ca_file)
    try:
        target.address()
    except ValueError as error:
        raise typer.BadParameter(str(error), param_hint="--mqtt") from None
    return target
