"""Backup and restore of the data directory: one archive file, checked before it is trusted.

What goes in: everything the cell keeps under its data directory (the journal,
the state snapshot, the calibrations, the workpiece library, tokens.json and
admin.token, a journal set aside as damaged), except what is rebuilt or is not
state: the logs (`logs/`), the lock, the journal's `-wal` and `-shm`, and
temporary files (names starting with a dot). The settings changed with PATCH
/settings are in `runtime-settings.json`, so they come back with a restore.

Why it is consistent while the server runs:

- the journal is copied with SQLite's online backup API, one step, in one read
  transaction: the copy is the journal at one commit, never half of one, and
  the writer is not held up (WAL). Its `.last-commit` record is written for
  the copy from the copy's own last commit, so the chain check passes on it,
  and the copy is checked in full (`verify.py`, every commit) before it is
  archived;
- every other file is written atomically by the server (temporary file,
  rename: server/storage/files.py), so a file opened is one version of it;
- the journal is copied first, then the files: a change to a file is on
  record in the journal before it is made (server/api/audit.py), so the files
  are never older than what the journal says happened to them.

The archive is a gzip'd tar with `manifest.json` first: the format, when it
was made, the journal's last commit, and each file's size and SHA-256. A
restore reads and checks all of it, then the journal's chain, before it
changes anything; it runs only while it holds the data directory's lock
(`data_lock.py`: never under a live server), only into an empty data
directory unless forced, and then what was there is moved aside
(`before-restore-<time>/`), never deleted. Files come back 0600 and
directories 0700, as the server makes them (`permissions.py`).
"""

from __future__ import annotations

import contextlib
import gzip
import hashlib
import io
import json
import os
import shutil
import sqlite3
import tarfile
import tempfile
import time
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import IO, Any

from server.storage.data_lock import LOCK_NAME, DataDirectoryLock
from server.storage.journal.commit_chain import LAST_COMMIT_SUFFIX, LastCommitFile
from server.storage.journal.verify import verify
from server.storage.permissions import DIRECTORY_MODE, FILE_MODE, private_directory

FORMAT = "glue-cell-backup"
VERSION = 1
MANIFEST = "manifest.json"
FILES = "data/"  # the data directory's files, under this prefix in the archive
ASIDE_PREFIX = "before-restore-"
STAGING_PREFIX = ".restore-"
SKIPPED_DIRECTORIES = ("logs",)
CHUNK = 1 << 20


class BackupError(Exception):
    """A backup or restore that cannot be made, in one line a technician can act on."""


@dataclass(frozen=True, slots=True)
class BackupSummary:
    archive: Path
    files: int
    journal_commit: int | None  # the copy's last commit; None: no journal yet
    journal_damage: list[str] = field(default_factory=list)  # what the full check found


@dataclass(frozen=True, slots=True)
class RestoreSummary:
    data_path: Path
    files: int
    journal_commit: int | None
    moved_aside: Path | None  # where what the data directory held went (--force)
    journal_damage: list[str] = field(default_factory=list)  # known at backup time


def journal_name(data_path: Path, journal_path: Path) -> str:
    """The journal's path inside the data directory; BackupError when it lies outside."""
    try:
        return journal_path.resolve().relative_to(data_path.resolve()).as_posix()
    except ValueError:
        raise BackupError(
            f"the journal ({journal_path}) is outside the data directory ({data_path}): "
            "backup and restore cover the data directory only; set analytics_database "
            "to a name inside it, or copy the journal by hand with the server stopped"
        ) from None


# --- backup ------------------------------------------------------------------


def create_backup(data_path: Path, journal_path: Path, archive: Path) -> BackupSummary:
    """Write a consistent copy of `data_path` to `archive` (a new file), server running or not."""
    if not data_path.is_dir():
        raise BackupError(f"there is no data directory at {data_path}")
    journal = journal_name(data_path, journal_path)
    if archive.exists():
        raise BackupError(f"{archive} exists already: choose a new name (nothing is overwritten)")
    if not archive.parent.is_dir():
        raise BackupError(f"there is no directory {archive.parent} to write {archive.name} into")
    if _inside(archive, data_path):
        raise BackupError(f"write the backup outside the data directory {data_path}")
    with tempfile.TemporaryDirectory(prefix=f".{archive.name}.", dir=archive.parent) as scratch:
        staged = Path(scratch) / "data"
        private_directory(staged)
        head, damage = _copy_journal(data_path / journal, staged / journal)
        names = [journal, journal + LAST_COMMIT_SUFFIX] if head is not None else []
        for name in _files_to_copy(data_path, journal):
            if _copy_file(data_path / name, staged / name):
                names.append(name)
        manifest = {
            "format": FORMAT,
            "version": VERSION,
            "created": time.time(),
            "journal": journal if head is not None else None,
            "journal_commit": head,
            "journal_damage": damage,
            "files": {name: _describe(staged / name) for name in sorted(names)},
        }
        _write_archive(archive, staged, manifest)
    return BackupSummary(archive, len(names), head, damage)


def _inside(path: Path, directory: Path) -> bool:
    return path.resolve().is_relative_to(directory.resolve())


def _files_to_copy(data_path: Path, journal: str) -> Iterator[str]:
    """Names (relative, POSIX) of the regular files to archive, journal's own excluded."""
    own = {journal, *(journal + s for s in ("-wal", "-shm", "-journal", LAST_COMMIT_SUFFIX))}
    for directory, subdirectories, files in os.walk(data_path):
        relative = Path(directory).relative_to(data_path)
        if relative == Path("."):
            subdirectories[:] = [
                d
                for d in subdirectories
                if d not in SKIPPED_DIRECTORIES and not d.startswith(ASIDE_PREFIX)
            ]
        subdirectories[:] = sorted(d for d in subdirectories if not d.startswith("."))
        for name in sorted(files):
            path = (relative / name).as_posix()
            if name.startswith(".") or path in own or path == LOCK_NAME:
                continue
            yield path


def _copy_file(source: Path, target: Path) -> bool:
    """Copy one file as it is now (False: it went meanwhile, or is no regular file)."""
    if source.is_symlink():
        return False  # the server makes none; one pointing elsewhere is not the cell's
    try:
        with source.open("rb") as handle:
            if not os.path.isfile(source):
                return False
            private_directory(target.parent)
            with _private_writer(target) as out:
                shutil.copyfileobj(handle, out, CHUNK)
    except FileNotFoundError:
        return False
    return True


def _private_writer(path: Path) -> IO[bytes]:
    return os.fdopen(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, FILE_MODE), "wb")


def _copy_journal(source: Path, target: Path) -> tuple[int | None, list[str]]:
    """The journal at one commit, with a last-commit record for that commit; checked in full.

    Returns the copy's last commit (None: no journal) and what the check found wrong.
    """
    if not source.is_file():
        return None, []
    private_directory(target.parent)
    _private_writer(target).close()
    try:
        live = sqlite3.connect(f"{source.resolve().as_uri()}?mode=ro", uri=True, timeout=30)
        copy = sqlite3.connect(target)
        try:
            live.backup(copy)  # pages=-1: every page in one step, one read transaction
            copy.execute("PRAGMA journal_mode=DELETE")  # one file; the server sets WAL again
            return _note_head(copy, target)
        finally:
            copy.close()
            live.close()
    except sqlite3.DatabaseError as exc:
        raise BackupError(f"SQLite cannot copy the journal {source}: {exc}") from None


def _note_head(copy: sqlite3.Connection, target: Path) -> tuple[int, list[str]]:
    """Check the copy (every commit) and write its last-commit record from its own head."""
    quick = copy.execute("PRAGMA quick_check").fetchone()
    if quick is None or quick[0] != "ok":
        raise sqlite3.DatabaseError(f"quick_check: {quick}")
    verdict = verify(copy, None, window=None)
    note = LastCommitFile(target)
    try:
        note.write(verdict.head)
    finally:
        note.close()
    return verdict.head.seq, [d.message for d in verdict.damage]


def _describe(path: Path) -> dict[str, Any]:
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        while chunk := handle.read(CHUNK):
            digest.update(chunk)
    return {"size": path.stat().st_size, "sha256": digest.hexdigest()}


def _write_archive(archive: Path, staged: Path, manifest: dict[str, Any]) -> None:
    """The manifest, then each file, into a temporary sibling; fsync; rename into place."""
    descriptor, temporary = tempfile.mkstemp(prefix=f".{archive.name}.", dir=archive.parent)
    try:
        with os.fdopen(descriptor, "wb") as handle:
            with tarfile.open(fileobj=handle, mode="w:gz") as tar:
                document = json.dumps(manifest, indent=2).encode()
                info = _member(MANIFEST, len(document))
                tar.addfile(info, io.BytesIO(document))
                for name in manifest["files"]:
                    path = staged / name
                    with path.open("rb") as source:
                        tar.addfile(_member(FILES + name, path.stat().st_size), source)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, archive)  # mkstemp's 0600: the archive holds admin.token
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def _member(name: str, size: int) -> tarfile.TarInfo:
    """A regular file's header that names no user and no time but the backup's."""
    info = tarfile.TarInfo(name)
    info.size = size
    info.mode = FILE_MODE
    info.mtime = int(time.time())
    return info


# --- restore -----------------------------------------------------------------


def restore_backup(
    archive: Path, data_path: Path, journal_path: Path, *, force: bool = False
) -> RestoreSummary:
    """Put the data directory back as `archive` holds it; nothing changes unless all of it
    checks out, and never while a server runs on `data_path`."""
    journal = journal_name(data_path, journal_path)
    manifest = read_manifest(archive)
    _check_archive(archive, manifest)  # every byte and the journal, before anything is touched
    if data_path.exists() and not data_path.is_dir():
        raise BackupError(f"{data_path} is not a directory")
    created = not data_path.exists()
    if not created:
        # A live server first: "in use, stop the server" is the refusal that helps; "add
        # --force" would not (the lock refuses a forced restore too).
        DataDirectoryLock(data_path, "restore").ensure_free()
    if not created and not force:
        _refuse_unless_empty(data_path)  # before the lock: a refusal leaves no trace
    private_directory(data_path)
    try:
        with DataDirectoryLock(data_path, "restore"):
            held = _held_entries(data_path)
            if not force:
                _refuse_unless_empty(data_path)  # again: filled meanwhile?
            staging = Path(tempfile.mkdtemp(prefix=STAGING_PREFIX, dir=data_path))
            try:
                _extract(archive, manifest, staging, journal)  # checked again as written
                aside = _move_aside(data_path, held) if held else None
                for entry in sorted(staging.iterdir()):
                    entry.replace(data_path / entry.name)
            finally:
                shutil.rmtree(staging, ignore_errors=True)
    except BaseException:
        if created:
            shutil.rmtree(data_path, ignore_errors=True)  # it held nothing before
        raise
    return RestoreSummary(
        data_path,
        len(manifest["files"]),
        manifest["journal_commit"],
        aside,
        list(manifest["journal_damage"]),
    )


def read_manifest(archive: Path) -> dict[str, Any]:
    """The archive's manifest, checked for shape; BackupError when it is no backup of ours."""
    try:
        with tarfile.open(archive, mode="r:gz") as tar:
            first = tar.next()
            if first is None or first.name != MANIFEST or not first.isfile():
                raise BackupError(f"{archive} is not a glue-server backup (no {MANIFEST} first)")
            extracted = tar.extractfile(first)
            assert extracted is not None  # a regular file
            manifest = json.loads(extracted.read())
    except FileNotFoundError:
        raise BackupError(f"there is no file {archive}") from None
    except (OSError, EOFError, tarfile.TarError, zlib.error, ValueError) as exc:
        raise BackupError(f"{archive} is not a readable backup: {exc}") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise BackupError(f"{archive} is not a glue-server backup")
    if manifest.get("version") != VERSION:
        raise BackupError(
            f"{archive} is a backup of format {manifest.get('version')!r}; this server "
            f"reads format {VERSION}"
        )
    files = manifest.get("files")
    if not isinstance(files, dict) or not all(
        isinstance(d, dict) and isinstance(d.get("sha256"), str) and isinstance(d.get("size"), int)
        for d in files.values()
    ):
        raise BackupError(f"{archive}: its manifest's file list is malformed")
    for name in files:
        _safe_name(archive, name)
    journal = manifest.get("journal")
    if journal is not None and (journal not in files or journal + LAST_COMMIT_SUFFIX not in files):
        raise BackupError(f"{archive}: the manifest names a journal the archive does not list")
    if not isinstance(manifest.get("journal_damage", []), list):
        raise BackupError(f"{archive}: its manifest's journal_damage is malformed")
    manifest.setdefault("journal_damage", [])
    manifest.setdefault("journal_commit", None)
    return manifest


def _safe_name(archive: Path, name: str) -> None:
    path = PurePosixPath(name)
    if (
        not name
        or path.is_absolute()
        or ".." in path.parts
        or path.parts[0] in (LOCK_NAME, *SKIPPED_DIRECTORIES)
        or any(part.startswith(".") for part in path.parts)
    ):
        raise BackupError(f"{archive}: refusing a file named {name!r}")


def _members(archive: Path, manifest: dict[str, Any]) -> Iterator[tuple[str, IO[bytes]]]:
    """Each listed file's name and content, in archive order; anything else refused."""
    expected = dict(manifest["files"])
    try:
        with tarfile.open(archive, mode="r:gz") as tar:
            tar.next()  # the manifest
            while (member := tar.next()) is not None:
                name = member.name.removeprefix(FILES)
                if not member.name.startswith(FILES) or name not in expected:
                    raise BackupError(f"{archive} holds {member.name!r}, not in its manifest")
                if not member.isfile():
                    raise BackupError(f"{archive}: {member.name!r} is not a regular file")
                del expected[name]
                content = tar.extractfile(member)
                assert content is not None
                yield name, content
    except (OSError, EOFError, tarfile.TarError, zlib.error) as exc:
        raise BackupError(f"{archive} is damaged: {exc}") from None
    if expected:
        raise BackupError(f"{archive} lacks {', '.join(sorted(expected))}, listed in its manifest")


def _checked_copy(
    archive: Path, name: str, content: IO[bytes], described: dict[str, Any], out: IO[bytes] | None
) -> None:
    """Read one member (into `out`, if given) and compare it with its manifest entry."""
    digest = hashlib.sha256()
    size = 0
    while True:
        try:
            chunk = content.read(CHUNK)
        except (EOFError, tarfile.TarError, zlib.error, gzip.BadGzipFile) as exc:
            raise BackupError(f"{archive} is damaged: {exc}") from None
        if not chunk:
            break
        digest.update(chunk)
        size += len(chunk)
        if out is not None:
            out.write(chunk)
    if size != described["size"] or digest.hexdigest() != described["sha256"]:
        raise BackupError(f"{archive} is damaged: {name} is not what was backed up (checksum)")


def _check_archive(archive: Path, manifest: dict[str, Any]) -> None:
    """Every member against its checksum, and the journal's chain, on a private copy of the
    journal in the temporary directory: nothing in the data directory is touched."""
    journal = manifest.get("journal")
    with tempfile.TemporaryDirectory(prefix="glue-restore-check-") as scratch:
        kept = {journal, f"{journal}{LAST_COMMIT_SUFFIX}"} if journal is not None else set()
        for name, content in _members(archive, manifest):
            target = Path(scratch) / PurePosixPath(name).name
            with _private_writer(target) if name in kept else contextlib.nullcontext() as out:
                _checked_copy(archive, name, content, manifest["files"][name], out)
        if journal is not None:
            _check_journal(Path(scratch) / PurePosixPath(journal).name, manifest)


def _extract(archive: Path, manifest: dict[str, Any], staging: Path, journal: str) -> None:
    """Every file into `staging` (0600, directories 0700), checked again as it is written;
    the archive's journal takes this server's journal name."""
    archived = manifest.get("journal")
    renamed = {}
    if archived is not None:
        renamed = {archived: journal, archived + LAST_COMMIT_SUFFIX: journal + LAST_COMMIT_SUFFIX}
    for name, content in _members(archive, manifest):
        target = staging / renamed.get(name, name)
        for parent in reversed(target.relative_to(staging).parents[:-1]):
            directory = staging / parent
            if not directory.is_dir():
                directory.mkdir(mode=DIRECTORY_MODE)
                os.chmod(directory, DIRECTORY_MODE)
        with _private_writer(target) as out:
            _checked_copy(archive, name, content, manifest["files"][name], out)
            out.flush()
            os.fsync(out.fileno())


def _check_journal(journal: Path, manifest: dict[str, Any]) -> None:
    """The restored journal reads, ends at the commit its record names, and shows no damage
    beyond what the backup itself reported."""
    if manifest.get("journal") is None:
        return
    try:
        noted = LastCommitFile(journal).read()
        connection = sqlite3.connect(f"{journal.resolve().as_uri()}?mode=ro", uri=True)
        try:
            quick = connection.execute("PRAGMA quick_check").fetchone()
            if quick is None or quick[0] != "ok":
                raise sqlite3.DatabaseError(f"quick_check: {quick}")
            verdict = verify(connection, noted, window=None)
        finally:
            connection.close()
    except (OSError, ValueError, sqlite3.DatabaseError) as exc:
        raise BackupError(f"the journal in the backup cannot be read: {exc}") from None
    known = set(manifest["journal_damage"])
    new = [d.message for d in verdict.damage if d.message not in known]
    if new or verdict.head.seq != manifest["journal_commit"]:
        found = "; ".join(new) or f"it ends at commit {verdict.head.seq}"
        raise BackupError(f"the journal in the backup does not check: {found}")


def _refuse_unless_empty(data_path: Path) -> None:
    held = _held_entries(data_path)
    if held:
        raise BackupError(
            f"{data_path} is not empty ({', '.join(held[:5])}"
            f"{', ...' if len(held) > 5 else ''}): restore into an empty data "
            "directory, or add --force to move what it holds aside first"
        )


def _held_entries(data_path: Path) -> list[str]:
    """What the data directory holds besides the lock, earlier set-asides and stagings."""
    return sorted(
        entry.name
        for entry in data_path.iterdir()
        if entry.name != LOCK_NAME and not entry.name.startswith((ASIDE_PREFIX, STAGING_PREFIX))
    )


def _move_aside(data_path: Path, held: list[str]) -> Path:
    """Move what the data directory held into `before-restore-<time>/` inside it."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    aside = data_path / f"{ASIDE_PREFIX}{stamp}"
    n = 1
    while aside.exists():
        aside = data_path / f"{ASIDE_PREFIX}{stamp}-{n}"
        n += 1
    aside.mkdir(mode=DIRECTORY_MODE)
    os.chmod(aside, DIRECTORY_MODE)
    for name in held:
        (data_path / name).replace(aside / name)
    return aside
