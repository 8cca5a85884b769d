"""The self-watch's memory and free-space warnings: raised once as the figure crosses its
threshold, cleared once it is back under it (so OPC UA's alarm goes inactive)."""

from __future__ import annotations

from pathlib import Path

from server.settings.watch import WatchSettings
from server.watch.system import DiskSpace, ProcessUse
from server.watch.watcher import CellWatch

MB = 1024**2


class Said:
    """What the watch raised and cleared, in order."""

    def __init__(self) -> None:
        self.said: list[tuple[str, str]] = []

    def warn(
        self,
        code: str,
        message: str,
        component: str,
        *,
        severity: str = "warning",
        standing: bool = False,
    ) -> None:
        assert standing  # each of these is cleared later
        self.said.append(("raised", code))

    def cleared(self, code: str, message: str, component: str) -> None:
        self.said.append(("cleared", code))


def watch(said: Said) -> CellWatch:
    settings = WatchSettings(memory_limit="100MB", free_space_warning="50MB")
    return CellWatch(
        lambda: settings,
        Path("."),
        dict,
        said.warn,
        image_pids=list,
        cleared=said.cleared,
    )


def use(resident_mb: int) -> ProcessUse:
    return ProcessUse(1, resident_mb * MB, None, None, None, None)


def disk(free_mb: int) -> DiskSpace:
    return DiskSpace(".", 1000 * MB, free_mb * MB)


def test_memory_warnings_clear_once_the_server_is_back_under_their_thresholds() -> None:
    said = Said()
    cell = watch(said)
    cell._judge(1.0, use(85), None, disk(500))  # over 80 %: MEMORY_HIGH
    cell._judge(2.0, use(101), None, disk(500))  # at the limit: the alert too
    cell._judge(3.0, use(101), None, disk(500))  # still: nothing again
    assert said.said == [("raised", "MEMORY_HIGH"), ("raised", "MEMORY_LIMIT_REACHED")]
    cell._judge(4.0, use(90), None, disk(500))  # under the limit, still high
    assert said.said[-1] == ("cleared", "MEMORY_LIMIT_REACHED")
    cell._judge(5.0, use(40), None, disk(500))
    assert said.said[-1] == ("cleared", "MEMORY_HIGH")
    count = len(said.said)
    cell._judge(6.0, use(40), None, disk(500))
    assert len(said.said) == count  # cleared once


def test_the_free_space_warning_clears_once_space_is_freed() -> None:
    said = Said()
    cell = watch(said)
    cell._judge(1.0, use(10), None, disk(20))
    cell._judge(2.0, use(10), None, disk(30))
    assert said.said == [("raised", "DISK_SPACE_LOW")]
    cell._judge(3.0, use(10), None, disk(60))
    cell._judge(4.0, use(10), None, disk(70))
    assert said.said == [("raised", "DISK_SPACE_LOW"), ("cleared", "DISK_SPACE_LOW")]
    cell._judge(5.0, use(10), None, disk(10))  # low again: raised again
    assert said.said[-1] == ("raised", "DISK_SPACE_LOW")
