"""`glue-server backup FILE` and `glue-server restore FILE`: the data directory in one archive.

The work is server/storage/backup.py's; this reads the settings the server
would (the data directory, the journal's name) and says in one line what was
done or why not. Exit 0 done, 1 refused (nothing changed), 2 bad usage.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from server.settings.load import SettingsRefused, load_settings
from server.storage.backup import BackupError, create_backup, restore_backup
from server.storage.data_lock import DataDirectoryBusy

COMMANDS = ("backup", "restore")


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="glue-server",
        description="Back up the data directory (while the server runs) or restore it "
        "(with the server stopped). See docs/operations-guide.md.",
    )
    commands = parser.add_subparsers(dest="command", required=True)
    backup = commands.add_parser("backup", help="write a consistent copy to a new archive FILE")
    restore = commands.add_parser("restore", help="put the data directory back from FILE")
    for command in (backup, restore):
        command.add_argument("file", type=Path, help="the archive (.tar.gz)")
        command.add_argument(
            "--data-dir", type=Path, help="the server's data directory (default ./data)"
        )
    restore.add_argument(
        "--force",
        action="store_true",
        help="restore into a data directory that is not empty (what it holds is moved "
        "aside into before-restore-<time>/ in it, not deleted)",
    )
    return parser.parse_args(argv)


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    overrides = {"data_path": args.data_dir} if args.data_dir else {}
    try:
        settings = load_settings(overrides)
    except SettingsRefused as exc:
        print(f"glue-server {args.command}: {exc}", file=sys.stderr)
        return 2
    journal = settings.journal_file
    try:
        if args.command == "backup":
            made = create_backup(settings.data_path, journal, args.file)
            print(
                f"backup written: {made.archive} ({made.files} files; "
                f"journal {_commit(made.journal_commit)})"
            )
            for damage in made.journal_damage:
                print(f"warning: the journal as copied: {damage}", file=sys.stderr)
        else:
            done = restore_backup(args.file, settings.data_path, journal, force=args.force)
            print(
                f"restored {done.data_path} from {args.file} ({done.files} files; "
                f"journal {_commit(done.journal_commit)})"
            )
            if done.moved_aside is not None:
                print(f"what {done.data_path} held before is in {done.moved_aside}")
            for damage in done.journal_damage:
                print(f"warning: found in the journal when it was backed up: {damage}")
    except (BackupError, DataDirectoryBusy) as exc:
        print(f"glue-server {args.command}: refused: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"glue-server {args.command}: failed: {exc}", file=sys.stderr)
        return 1
    return 0


def _commit(seq: int | None) -> str:
    return "none" if seq is None else f"up to commit {seq}"
