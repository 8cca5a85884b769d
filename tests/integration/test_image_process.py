"""The image process (server/vision/process.py): a real child process, frames in shared memory."""

from __future__ import annotations

import asyncio
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from server.common.errors import OperationError
from server.vision.process import NICE, ImageProcess, ImageProcessFailed
from tests.processes import has_ended, run_python


# What the child runs: module-level, as the image process requires.
def whose(frame: np.ndarray) -> tuple[int, float]:
    return os.getpid(), float(frame.mean())


def brighter(frame: np.ndarray, by: int) -> np.ndarray:
    return (frame.astype(np.int16) + by).clip(0, 255).astype(np.uint8)


def slow_sum(frame: np.ndarray, seconds: float, report: str = "") -> int:
    time.sleep(seconds)
    total = int(frame.sum())
    if report:  # what the child saw, for a caller that left
        Path(report).write_text(str(total))
    return total


def refuses(frame: np.ndarray) -> None:
    raise OperationError("MARKER_NOT_FOUND", "marker 4 not found", recoverable=True)


class Unpicklable(Exception):
    def __init__(self, a: int, b: int) -> None:  # args (a message) no longer rebuild it
        super().__init__(f"{a} and {b}")


def raises_unpicklable() -> None:
    raise Unpicklable(1, 2)


def dies() -> None:
    os._exit(3)


def wrong_shape(frame: np.ndarray) -> np.ndarray:
    return frame[:10]


def unique_mb() -> float:
    """This process's unique memory (Private_Clean + Private_Dirty), in MB."""
    fields = {}
    for line in Path("/proc/self/smaps_rollup").read_text().splitlines():
        name, _, value = line.partition(":")
        fields[name] = value
    return sum(int(fields[name].split()[0]) for name in ("Private_Clean", "Private_Dirty")) / 1024


def kept_after_frames() -> float:
    """MB the child still holds after drawing and dropping two large frames.

    The first, freed, would raise glibc's default mmap threshold above the second's
    size, so the second would come from the heap, and stay there once freed."""
    before = unique_mb()
    for size_mb in (24, 20):
        frame = np.ones(size_mb * 2**20, np.uint8)  # written: its pages are really there
        del frame
    return unique_mb() - before


def niceness() -> int:
    return os.nice(0)


def main_module_file() -> str | None:
    """Where the child's main module came from: None when it ran none of the parent's."""
    return getattr(sys.modules["__main__"], "__file__", None)


@pytest.fixture
def images() -> Iterator[ImageProcess]:
    process = ImageProcess()
    yield process
    process.close()


def frame(value: int, shape: tuple[int, ...] = (1080, 1920, 3)) -> np.ndarray:
    rng = np.random.default_rng(value)
    return rng.integers(0, 200, shape, dtype=np.uint8)


async def test_a_frame_is_worked_on_in_another_process_and_comes_back_whole(
    images: ImageProcess,
) -> None:
    image = frame(1)
    pid, mean = await images.call(whose, frame=image)
    assert pid != os.getpid()
    assert mean == pytest.approx(float(image.mean()))

    out = await images.call(brighter, 30, frame=image, frame_out=(image.shape, np.uint8))
    assert np.array_equal(out, brighter(image, 30))
    smaller = frame(2, (480, 640))  # another size through the same blocks
    out = await images.call(brighter, 5, frame=smaller, frame_out=(smaller.shape, np.uint8))
    assert np.array_equal(out, brighter(smaller, 5))


async def test_the_child_works_below_the_servers_priority(images: ImageProcess) -> None:
    """Below the control loop, yet not so far that any busy process starves the cycle's
    own image work (server/vision/process.py, NICE)."""
    assert await images.call(niceness) == min(19, os.nice(0) + NICE)


async def test_an_operation_error_in_the_child_reaches_the_caller_whole(
    images: ImageProcess,
) -> None:
    with pytest.raises(OperationError) as raised:
        await images.call(refuses, frame=frame(3))
    assert (raised.value.code, str(raised.value), raised.value.recoverable) == (
        "MARKER_NOT_FOUND",
        "marker 4 not found",
        True,
    )
    with pytest.raises(RuntimeError, match="Unpicklable: 1 and 2"):
        await images.call(raises_unpicklable)
    with pytest.raises(ValueError, match="not the frame of"):
        await images.call(wrong_shape, frame=frame(4), frame_out=((1080, 1920, 3), np.uint8))
    pid, _ = await images.call(whose, frame=frame(5))  # the child lived through all three
    assert pid != os.getpid()


async def test_a_child_that_died_is_replaced_on_the_next_call(images: ImageProcess) -> None:
    first, _ = await images.call(whose, frame=frame(6))
    with pytest.raises(ImageProcessFailed, match="next call starts a new one"):
        await images.call(dies)
    second, mean = await images.call(whose, frame=frame(7))
    assert second not in (first, os.getpid())
    assert mean == pytest.approx(float(frame(7).mean()))


async def test_a_cancelled_call_keeps_its_frame_until_the_child_is_done(
    images: ImageProcess, tmp_path: Path
) -> None:
    """The caller of the slow call leaves at once; the child still reads its own frame, and
    a call made meanwhile gets a block of its own, never the one being read."""
    slow_frame, quick_frame = frame(8), frame(9)
    seen = tmp_path / "seen"
    slow = asyncio.ensure_future(images.call(slow_sum, 0.5, str(seen), frame=slow_frame))
    await asyncio.sleep(0.2)  # the child is working on it
    slow.cancel()
    with pytest.raises(asyncio.CancelledError):
        await slow
    quick = await images.call(slow_sum, 0.0, frame=quick_frame)
    assert quick == int(quick_frame.sum())
    later = await images.call(slow_sum, 0.0, frame=slow_frame)  # once the first call ended
    assert later == int(slow_frame.sum())
    assert seen.read_text() == str(int(slow_frame.sum()))  # its frame was never overwritten


async def test_closing_ends_a_child_stuck_in_a_call(images: ImageProcess) -> None:
    """A call that never ends must not hold the server's exit: close ends the child."""
    child, _ = await images.call(whose, frame=frame(10))
    stuck = asyncio.ensure_future(images.call(slow_sum, 3600.0, frame=frame(11)))
    await asyncio.sleep(0.2)  # the child is in the call
    images.close()
    with pytest.raises(ImageProcessFailed):
        await stuck
    assert has_ended(child)
    again, _ = await images.call(whose, frame=frame(12))  # a later call starts afresh
    assert again != child


async def test_the_child_gives_freed_frames_back(images: ImageProcess) -> None:
    kept = await images.call(kept_after_frames)
    assert kept < 5, f"the child kept {kept:.1f} MB of frames it had freed"


SCRIPT = """
import asyncio
from server.vision.process import IMAGE_PROCESS
from tests.integration.test_image_process import main_module_file

if __name__ == "__main__":
    print(asyncio.run(IMAGE_PROCESS.call(main_module_file)))
    IMAGE_PROCESS.close()
"""


def test_the_child_runs_none_of_the_parents_main_module(tmp_path: Path) -> None:
    """A script of its own (glue-server's, one that runs a cell) is not run again in the
    child: it would import the whole server there for nothing."""
    script = tmp_path / "runs_a_cell.py"
    script.write_text(SCRIPT)
    done = run_python(str(script))
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "None"
