"""A data directory on a file system a test can fill up and free again, for a server process.

Where the test may mount one (root, or a container with the right), it is a real
size-limited tmpfs: `fill` writes a filler file until the kernel says ENOSPC,
`free` deletes it. Elsewhere (a CI runner without mount rights) it falls back to
a file-size limit on the server process (RLIMIT_FSIZE, with SIGXFSZ ignored so a
write past it fails with EFBIG instead of killing the process): `fill` lowers the
running server's limit to one byte with prlimit, so every write that extends or
rewrites a file fails, `free` lifts it. Either way the server's own code meets a
real failing `write(2)`; nothing is mocked.
"""

from __future__ import annotations

import contextlib
import errno
import os
import resource
import shutil
import signal
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path

MIB = 1024 * 1024
_CHUNKS = (MIB, 64 * 1024, 4096, 512, 1)  # the filler's writes, down to the last byte


class SmallDisk:
    """A directory whose file system can be filled (`fill`) and freed (`free`)."""

    kind = ""

    def __init__(self, path: Path, size: int) -> None:
        self.path = path
        self.size = size
        self.pid: int | None = None  # the server process, once `attach`ed

    def preexec(self) -> Callable[[], None] | None:
        """What the server process runs before the server (None: nothing)."""
        return None

    def attach(self, pid: int) -> None:
        """The server process the limits apply to."""
        self.pid = pid

    def fill(self) -> None:
        raise NotImplementedError

    def free(self) -> None:
        raise NotImplementedError


class Tmpfs(SmallDisk):
    """A size-limited tmpfs mounted at `path`."""

    kind = "tmpfs"

    def fill(self) -> None:
        descriptor = os.open(self.path / "filler", os.O_WRONLY | os.O_CREAT | os.O_APPEND)
        try:
            for chunk in _CHUNKS:
                block = b"\0" * chunk
                while True:
                    try:
                        os.write(descriptor, block)
                    except OSError as exc:
                        if exc.errno != errno.ENOSPC:
                            raise
                        break
        finally:
            os.close(descriptor)

    def free(self) -> None:
        (self.path / "filler").unlink(missing_ok=True)


class FileSizeLimit(SmallDisk):
    """No mount: RLIMIT_FSIZE on the server process stands for the disk's size."""

    kind = "file-size limit"

    def preexec(self) -> Callable[[], None]:
        size = self.size

        def limit() -> None:
            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG, not death
            resource.setrlimit(resource.RLIMIT_FSIZE, (size, resource.RLIM_INFINITY))

        return limit

    def _limit(self, soft: int) -> None:
        assert self.pid is not None, "attach the server process first"
        resource.prlimit(self.pid, resource.RLIMIT_FSIZE, (soft, resource.RLIM_INFINITY))

    def fill(self) -> None:
        self._limit(1)

    def free(self) -> None:
        self._limit(self.size)


def _mount_tmpfs(path: Path, size: int) -> bool:
    """Mount a tmpfs of `size` bytes at `path`; False when this machine does not let us."""
    mount = shutil.which("mount")
    if mount is None:
        return False
    try:
        done = subprocess.run(
            [mount, "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
            capture_output=True,
            timeout=30,
        )
    except (OSError, subprocess.TimeoutExpired):
        return False
    return done.returncode == 0


def _unmount(path: Path) -> None:
    umount = shutil.which("umount") or "umount"
    if subprocess.run([umount, str(path)], capture_output=True, timeout=30).returncode != 0:
        subprocess.run([umount, "-l", str(path)], capture_output=True, timeout=30)


@contextlib.contextmanager
def small_disk(where: Path, size: int) -> Iterator[SmallDisk]:
    """A `size`-byte file system at `where` (created): a tmpfs if we may mount, else a limit."""
    where.mkdir(parents=True, exist_ok=True)
    if not _mount_tmpfs(where, size):
        yield FileSizeLimit(where, size)
        return
    try:
        yield Tmpfs(where, size)
    finally:
        _unmount(where)
