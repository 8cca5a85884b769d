"""What the cell's processes use, read from Linux's /proc: CPU, memory, open files, threads.

Why /proc and not a library: each figure is one small file the kernel keeps per process
(`status` for resident memory and threads, `smaps_rollup` for the unique memory, `fd/`
for open files, `stat` for CPU time), readable for the server and its own child, the
image process. Unique memory is what the process alone holds (Private_* of its
mappings): what ending it would give back, where resident memory also counts libraries
shared with others. A figure that cannot be read (another system, a process that just
ended) is None, never an error: watching must not fail the cell.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path

PROC = Path("/proc")
KB = 1024
TICKS_PER_S = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


@dataclass(frozen=True)
class ProcessUse:
    """One process's figures at one moment."""

    pid: int
    resident_bytes: int | None
    unique_bytes: int | None
    threads: int | None
    open_files: int | None
    cpu_seconds: float | None

    def as_dict(self) -> dict[str, int | float | None]:
        return {
            "pid": self.pid,
            "resident_bytes": self.resident_bytes,
            "unique_bytes": self.unique_bytes,
            "threads": self.threads,
            "open_files": self.open_files,
            "cpu_seconds": None if self.cpu_seconds is None else round(self.cpu_seconds, 3),
        }


def _fields(path: Path) -> dict[str, str]:
    """`Name: value` lines of a /proc file, or {} when it cannot be read."""
    try:
        text = path.read_text(encoding="ascii", errors="replace")
    except OSError:
        return {}
    fields = {}
    for line in text.splitlines():
        name, _, value = line.partition(":")
        fields[name.strip()] = value.strip()
    return fields


def _kb(value: str | None) -> int | None:
    """'1234 kB' → bytes."""
    if not value:
        return None
    try:
        return int(value.split()[0]) * KB
    except (ValueError, IndexError):
        return None


def unique_bytes(pid: int) -> int | None:
    """The process's private memory: Private_Clean + Private_Dirty (+ Private_Hugetlb)."""
    rollup = _fields(PROC / str(pid) / "smaps_rollup")
    parts = [_kb(value) for name, value in rollup.items() if name.startswith("Private_")]
    known = [part for part in parts if part is not None]
    return sum(known) if known else None


def cpu_seconds(pid: int) -> float | None:
    """User plus system CPU time the process has used (fields 14 and 15 of `stat`)."""
    try:
        text = (PROC / str(pid) / "stat").read_text(encoding="ascii", errors="replace")
    except OSError:
        return None
    # The command name (field 2) is in parentheses and may hold spaces: split after it.
    rest = text.rpartition(")")[2].split()
    try:
        return (int(rest[11]) + int(rest[12])) / TICKS_PER_S
    except (ValueError, IndexError):
        return None


def open_files(pid: int) -> int | None:
    try:
        return len(os.listdir(PROC / str(pid) / "fd"))
    except OSError:
        return None


def process_use(pid: int) -> ProcessUse:
    """Everything the watch reads of one process (each figure None if unreadable)."""
    status = _fields(PROC / str(pid) / "status")
    threads = status.get("Threads")
    return ProcessUse(
        pid=pid,
        resident_bytes=_kb(status.get("VmRSS")),
        unique_bytes=unique_bytes(pid),
        threads=int(threads) if threads and threads.isdigit() else None,
        open_files=open_files(pid),
        cpu_seconds=cpu_seconds(pid),
    )


@dataclass(frozen=True)
class DiskSpace:
    """The disk holding a directory: its size and what is free for the cell's user."""

    path: str
    total_bytes: int
    free_bytes: int

    def as_dict(self) -> dict[str, int | str]:
        return {"path": self.path, "total_bytes": self.total_bytes, "free_bytes": self.free_bytes}


def disk_space(path: Path) -> DiskSpace | None:
    try:
        usage = shutil.disk_usage(path)
    except OSError:
        return None
    return DiskSpace(str(path), usage.total, usage.free)
