"""`glue-server diagnose FILE`: the diagnostic bundle, from the data directory alone.

It reads what the server would (the settings, the journal, the log) and needs
no running server, so it works on a cell that does not start; the live device
health is in GET /diagnostics on a running one. Exit 0 written, 1 failed, 2 bad
usage or settings.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from server.diagnostics.bundle import archive, collect
from server.settings.load import SettingsRefused, load_settings

COMMAND = "diagnose"


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog=f"glue-server {COMMAND}",
        description="Write the diagnostic bundle (version, settings with secrets masked, the "
        "newest faults with their context and stack, the journal's check, the log's end) "
        "to FILE, a new .tar.gz. See docs/operations-guide.md.",
    )
    parser.add_argument("file", type=Path, help="the archive to write (.tar.gz; must not exist)")
    parser.add_argument(
        "--data-dir", type=Path, help="the server's data directory (default ./data)"
    )
    return parser.parse_args(argv)


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    overrides = {"data_path": args.data_dir} if args.data_dir else {}
    try:
        settings = load_settings(overrides)
    except SettingsRefused as exc:
        print(f"glue-server {COMMAND}: {exc}", file=sys.stderr)
        return 2
    files = collect(settings, None, f"glue-server {COMMAND}")
    name = args.file.name.removesuffix(".tar.gz").removesuffix(".tgz") or "diagnostics"
    try:
        # 0600 from the start: settings name the cell's network; the bundle is for support
        with os.fdopen(
            os.open(args.file, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600), "wb"
        ) as out:
            out.write(archive(files, name))
    except OSError as exc:
        print(f"glue-server {COMMAND}: failed: {exc}", file=sys.stderr)
        return 1
    print(f"diagnostic bundle written: {args.file} ({len(files)} files)")
    return 0
