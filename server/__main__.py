"""glue-server: run the cell server (simulated cell unless hardware is configured)."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any

import uvicorn

from server.api.connection_guard import ConnectionLimits, guarded_http_protocol
from server.bootstrap import tls
from server.bootstrap.app import create_app
from server.bootstrap.logging_setup import configure as configure_logging
from server.cli import backup as backup_cli
from server.cli import diagnose as diagnose_cli
from server.common.build import package_version
from server.common.errors import ConfigurationError
from server.common.runtime import close_on_shutdown, limit_malloc_arenas, raise_open_file_limit
from server.settings.load import SettingsRefused, load_settings, unknown_variables
from server.settings.model import Settings
from server.storage.data_lock import DataDirectoryBusy, DataDirectoryLock
from server.storage.permissions import private_directory
from server.vision.process import IMAGE_PROCESS

SETTINGS_HELP = """\
settings, highest priority first:
  the command line     --data-dir (data_path); --host and --port are only here
  the environment      GLUE_APP_<NAME>, e.g. GLUE_APP_SHIFT_HOURS=12; lists
                       and tuples as JSON; the hardware ones also as ROBOT_IP,
                       VISION_CAMERA_ID, GLUE_CONTROLLER_PORT
  a JSON file          named by GLUE_APP_CONFIG_PATH, keys as the names above
  the defaults
No .env file is read. Every setting, its variable, default and accepted values:
docs/settings.md. A bad value stops the start (exit 2) with one line naming
it; a GLUE_APP_ variable that names no setting is a warning."""


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="glue-server",
        description="Control server for a glue-spraying robot cell. Without hardware\n"
        "settings (ROBOT_IP, GLUE_CONTROLLER_PORT, VISION_CAMERA_ID) it starts the\n"
        "simulators on loopback and drives them through the real protocol clients.\n"
        "Also: glue-server backup FILE, glue-server restore FILE, glue-server diagnose\n"
        "FILE (see their --help).",
        epilog=SETTINGS_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {package_version()}")
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=8000, help="HTTP port (default 8000)")
    parser.add_argument(
        "--data-dir", type=Path, help="where state and journals live (default ./data)"
    )
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    limit_malloc_arenas()  # before any thread allocates
    words = sys.argv[1:] if argv is None else argv
    if words[:1] and words[0] in backup_cli.COMMANDS:  # glue-server backup|restore FILE
        raise SystemExit(backup_cli.main(words))
    if words[:1] == [diagnose_cli.COMMAND]:  # glue-server diagnose FILE
        raise SystemExit(diagnose_cli.main(words[1:]))
    args = parse_args(argv)
    overrides = {"data_path": args.data_dir} if args.data_dir else {}
    misspelt = unknown_variables()
    try:
        settings = load_settings(overrides)
    except SettingsRefused as exc:  # before logging is set up: straight to stderr
        for warning in misspelt:  # the typo may be why the value is not the one meant
            print(f"glue-server: warning: {warning}", file=sys.stderr)
        print(f"glue-server: cannot start: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    private_directory(settings.data_path)  # 0700; a looser one is tightened by the cell
    try:  # held until the process ends: one server per data directory, no restore under it
        lock = DataDirectoryLock(settings.data_path, "server").acquire()
    except DataDirectoryBusy as exc:
        print(f"glue-server: cannot start: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    log_file = configure_logging(settings)
    log = logging.getLogger(__name__)
    log.info("logging to %s", log_file)
    for warning in misspelt:
        log.warning("%s", warning)
    if (clear := tls.plain_http_warning(args.host, settings)) is not None:
        log.warning("%s", clear)
    try:
        tls.check_files(settings)  # before the cell starts: one line, not uvicorn's traceback
        # This process is the server's: the collector tuned (server/bootstrap/latency.py).
        app = create_app(settings, tune_process=True)
        if settings.opcua_endpoint is not None:  # a port in use: one line now, not a traceback
            from server.opcua.interface import check_endpoint_free

            check_endpoint_free(settings.opcua_endpoint)
    except ConfigurationError as exc:  # one line, on the console and in the log file
        log.critical("cannot start: %s", exc)
        raise SystemExit(2) from None
    files = raise_open_file_limit()
    logging.getLogger(__name__).info("open-file limit %d", files)
    close_on_shutdown(app, IMAGE_PROCESS.close)  # the image process ends with the app
    uvicorn.run(
        app,
        host=args.host,
        port=args.port,
        log_level=settings.logging_level.lower(),
        log_config=None,  # keep the cell's handlers: uvicorn logs through them
        **uvicorn_options(settings),
    )
    lock.release()


def uvicorn_options(settings: Settings) -> dict[str, Any]:
    """How the server is served; tests and benchmarks serve it the same way."""
    return {
        "ws": "websockets-sansio",
        "ws_max_size": 64 * 1024,
        # The state messages are small and go to every client: compressing each one
        # per connection costs a third of the fan-out's CPU and saves a LAN nothing.
        "ws_per_message_deflate": False,
        "ws_ping_interval": settings.ws_ping_interval,
        "ws_ping_timeout": settings.ws_ping_interval,
        "timeout_graceful_shutdown": 5,
        # uvicorn has no header timeout and no bound on connections: its HTTP protocol
        # with both (server/api/connection_guard.py), and idle keep-alives closed.
        "http": guarded_http_protocol(ConnectionLimits.of(settings)),
        "timeout_keep_alive": settings.http_keepalive_timeout,
        # uvicorn would otherwise replace a loopback peer's address with whatever its
        # X-Forwarded-For says, before the app sees it. The app reads forwarded
        # addresses itself, from trusted_proxies only (server/security/forwarded.py).
        "proxy_headers": False,
        **tls.uvicorn_options(settings),  # https and wss when tls_cert_file is set
    }


if __name__ == "__main__":
    main()
