"""Image work in a child process, so a frame's analysis never holds the server's interpreter lock.

Why a process and not a thread: marker detection, outline fitting and the
simulated camera's rendering are long runs of numpy and OpenCV calls with
Python between them. On a thread they hold the interpreter lock for up to
several ms at a time, and the event loop (an e-stop's request among what it
serves) waits for them: with robot calibrations running and every thread of the
server on one core, the loop's lag at p99 is about five times longer with the
work on threads than with it here. A process competes for the core through the
kernel's scheduler, not for the lock, and runs a little below the server
(`NICE`): on a shared core the control loop gets about three quarters of it.
Not at the lowest priority: much of the work is the cycle's own (the frame
before a run, the inspection after it), and at nice 19 any busy process at the
default priority (a browser, another job on the machine) leaves it about a
seventieth of a core, and a part's cycle beside a busy loop on every core takes
five times as long; at nice 5 it keeps a quarter of a shared core, the cycle
holds, and the e-stop during vision work is as fast (docs/benchmarks.md, "A
part's cycle").

How frames cross: through shared memory, never pickled. Pickling a 1920×1080
colour frame holds the lock 2.5 ms; `np.copyto` into a shared block lets it
go. A call's frame goes in that way and, when the call gives a frame back
(`frame_out`), comes out that way too; everything else (arguments, results,
exceptions) is pickled, so it must be small and picklable.

One child does the work, one call after another, for the whole server
process: a cell with the simulated camera starts it as it starts (`warm_up`;
its imports take a second or so, once: the camera draws its frames there), one
with a real camera on its first call (a calibration, a run), and a child that
died is replaced on the next call. It is
started with `spawn`, but without the parent's main module: `spawn` would
import it again in the child (for `glue-server`, its script, and through it the
whole server: the web framework, the protocol stacks, the settings, some 30 MB
and a second of the start-up's CPU) for nothing, as the child runs only the
module-level functions it is handed, each imported by its own module's name.

A call cancelled by its caller (an e-stop ending the operation) cannot stop
the child's work: the caller goes on at once, and the call's shared block is
reused only once the child is done with it.
"""

from __future__ import annotations

import asyncio
import atexit
import concurrent.futures
import contextlib
import ctypes
import ctypes.util
import gc
import multiprocessing
import multiprocessing.connection
import multiprocessing.context
import os
import pickle
import signal
import threading
from collections.abc import Callable
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from multiprocessing import popen_spawn_posix, shared_memory, spawn
from typing import Any, TypeVar

import numpy as np

T = TypeVar("T")

NICE = 5  # below the server's control loop, not below every other process (docstring)


class ImageProcessFailed(RuntimeError):
    """The child process ended in the middle of a call (killed, out of memory)."""


@dataclass(frozen=True, slots=True)
class FrameSlot:
    """Where a frame lies in shared memory, as the child is told."""

    name: str
    shape: tuple[int, ...]
    dtype: str


class _Region:
    """A shared memory block that grows to the largest frame it has carried (parent side)."""

    def __init__(self) -> None:
        self._memory: shared_memory.SharedMemory | None = None

    def slot(self, shape: tuple[int, ...], dtype: np.dtype[Any]) -> FrameSlot:
        size = max(int(np.prod(shape)) * dtype.itemsize, 1)
        if self._memory is None or self._memory.size < size:
            self.release()
            self._memory = shared_memory.SharedMemory(create=True, size=size)
        return FrameSlot(self._memory.name, tuple(shape), dtype.str)

    def view(self, slot: FrameSlot) -> np.ndarray:
        assert self._memory is not None and self._memory.name == slot.name
        return np.ndarray(slot.shape, np.dtype(slot.dtype), buffer=self._memory.buf)

    def release(self) -> None:
        if self._memory is not None:
            with contextlib.suppress(BufferError):  # a view still held: unmapped when it goes
                self._memory.close()
            with contextlib.suppress(FileNotFoundError):
                self._memory.unlink()
            self._memory = None


class _Block:
    """One call's way in and way out."""

    def __init__(self) -> None:
        self.into = _Region()
        self.out = _Region()

    def release(self) -> None:
        self.into.release()
        self.out.release()


_PREPARATION = spawn.get_preparation_data
_launching = threading.Lock()


def _preparation_without_main(name: str) -> dict[str, Any]:
    data = _PREPARATION(name)
    data.pop("init_main_from_name", None)
    data.pop("init_main_from_path", None)
    return data


class _PopenWithoutMain(popen_spawn_posix.Popen):
    """`spawn`'s launch, with the main module left out of what the child prepares."""

    def _launch(self, process_obj: Any) -> None:
        with _launching:  # multiprocessing reads the preparation from its module: briefly ours
            spawn.get_preparation_data = _preparation_without_main
            try:
                super()._launch(process_obj)  # type: ignore[misc]  # not in the stubs
            finally:
                spawn.get_preparation_data = _PREPARATION


class _ProcessWithoutMain(multiprocessing.context.SpawnProcess):
    @staticmethod
    def _Popen(process_obj: Any) -> _PopenWithoutMain:
        return _PopenWithoutMain(process_obj)


class _SpawnWithoutMain(multiprocessing.context.SpawnContext):
    Process = _ProcessWithoutMain


class ImageProcess:
    """A child process for image work, shared by every caller in this process."""

    def __init__(self) -> None:
        self._pool: concurrent.futures.ProcessPoolExecutor | None = None
        self._idle: list[_Block] = []
        self._all: list[_Block] = []
        self._lock = threading.Lock()  # callers on several event loops (tests) share it

    async def call(
        self,
        fn: Callable[..., T],
        *args: Any,
        frame: np.ndarray | None = None,
        frame_out: tuple[tuple[int, ...], Any] | None = None,
    ) -> T:
        """`fn(frame, *args)` (or `fn(*args)` without a frame), run in the child.

        `fn` must be a module-level function. With `frame_out=(shape, dtype)`, fn
        returns an array of that shape, which comes back through shared memory.
        """
        # The child cannot be stopped mid-call: a cancelled caller leaves at once, and the
        # call goes on to its end, so its block is given back only once nothing reads it.
        calling = asyncio.ensure_future(self._call(fn, args, frame, frame_out))
        calling.add_done_callback(_retrieve)
        return await asyncio.shield(calling)

    async def _call(
        self,
        fn: Callable[..., Any],
        args: tuple[Any, ...],
        frame: np.ndarray | None,
        frame_out: tuple[tuple[int, ...], Any] | None,
    ) -> Any:
        block = self._take()
        try:
            into = out = None
            if frame is not None:
                into = block.into.slot(frame.shape, frame.dtype)
                await asyncio.to_thread(np.copyto, block.into.view(into), frame)
            if frame_out is not None:
                out = block.out.slot(tuple(frame_out[0]), np.dtype(frame_out[1]))
            pool, job = self._submit(_run_in_child, fn, args, into, out)
            try:
                result = await asyncio.wrap_future(job)
            except BrokenProcessPool as exc:
                self._forget_pool(pool)
                raise ImageProcessFailed(
                    "the image process ended in the middle of a call; "
                    "the next call starts a new one"
                ) from exc
            if out is None:
                return result
            image = np.empty(out.shape, np.dtype(out.dtype))
            await asyncio.to_thread(np.copyto, image, block.out.view(out))
            return image
        finally:
            self._give_back(block)

    def warm_up(self) -> None:
        """Start the child now (it imports numpy and OpenCV), not on the first frame."""
        self._submit(_run_in_child, os.getpid, (), None, None)

    def pids(self) -> list[int]:
        """The child's process id, while it runs (the cell's self-watch reads its memory)."""
        with self._lock:
            pool = self._pool
        processes = getattr(pool, "_processes", None) or {}
        return [pid for pid, child in list(processes.items()) if child.is_alive()]

    def close(self) -> None:
        """End the child and free the shared memory (at exit; a later call starts afresh).

        The child is ended, not waited for: a call stuck in it must not hold the
        server's exit.
        """
        with self._lock:
            pool, self._pool = self._pool, None
            blocks, self._all, self._idle = self._all, [], []
        if pool is not None:
            children = list(getattr(pool, "_processes", {}).values())
            for child in children:
                child.terminate()
            pool.shutdown(wait=True, cancel_futures=True)  # quick: its child has ended
            del pool
            gc.collect()  # its queues' semaphores are freed now, not left to be warned of
        for block in blocks:
            block.release()

    # --- internals ---------------------------------------------------------------------------

    def _submit(
        self, *call: Any
    ) -> tuple[concurrent.futures.ProcessPoolExecutor, concurrent.futures.Future[Any]]:
        """The call handed to the child, and the pool that has it (replaced if it broke)."""
        with self._lock:
            if self._pool is None:
                self._pool = concurrent.futures.ProcessPoolExecutor(
                    max_workers=1,
                    mp_context=_SpawnWithoutMain(),
                    initializer=_child_starts,
                )
            pool = self._pool
        try:
            return pool, pool.submit(*call)
        except BrokenProcessPool:
            self._forget_pool(pool)
            return self._submit(*call)

    def _forget_pool(self, pool: concurrent.futures.ProcessPoolExecutor) -> None:
        """A broken pool is let go (the next call starts another), once."""
        with self._lock:
            if pool is not self._pool:
                return  # already replaced by a call before this one
            self._pool = None
        pool.shutdown(wait=False, cancel_futures=True)

    def _take(self) -> _Block:
        with self._lock:
            if self._idle:
                return self._idle.pop()
            block = _Block()
            self._all.append(block)
            return block

    def _give_back(self, block: _Block) -> None:
        with self._lock:
            if block in self._all:
                self._idle.append(block)


def _retrieve(task: asyncio.Future[Any]) -> None:
    """A cancelled caller's call still ends; its outcome is read so nothing is logged as lost."""
    if not task.cancelled():
        task.exception()


# --- in the child --------------------------------------------------------------------------

_attached: dict[str, shared_memory.SharedMemory] = {}  # oldest first
ATTACHED_AT_MOST = 16  # two per call under way; more only once blocks grew

M_MMAP_THRESHOLD = -3  # glibc's mallopt parameter number
MMAP_THRESHOLD = 1 << 17


def _large_blocks_given_back() -> None:
    """Frames, images and their crops (128 KiB and more) mapped apart, so freeing one
    gives it back.

    glibc raises its mmap threshold each time such a block is freed, up to 32 MiB;
    past that, every frame the child draws or reads comes from the heap, and the heap
    keeps what they leave: with the threshold raised the child held about 200 MB
    more than it used. Fixed, it never rises (server/common/runtime.py does the same
    for the server). Elsewhere than glibc nothing is done.
    """
    name = ctypes.util.find_library("c")
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(name).mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)


def _child_starts() -> None:
    """Ctrl-C is the server's to handle; the child works at NICE, gives freed frames back
    to the kernel, and ends with the server.

    Why the watch: the child holds both ends of its call queue, so a server killed
    outright (SIGKILL, out of memory) would leave it waiting for work forever, with its
    shared memory kept. The parent's sentinel becomes ready when the server is gone.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _large_blocks_given_back()
    with contextlib.suppress(OSError):
        os.nice(NICE)
    parent = multiprocessing.parent_process()
    if parent is not None:
        watch = threading.Thread(target=_end_with, args=(parent.sentinel,), daemon=True)
        watch.start()


def _end_with(sentinel: int) -> None:
    multiprocessing.connection.wait([sentinel])
    os._exit(0)


def _view(slot: FrameSlot) -> np.ndarray:
    memory = _attached.get(slot.name)
    if memory is None:
        if len(_attached) >= ATTACHED_AT_MOST:  # the oldest: a block the parent has replaced
            _attached.pop(next(iter(_attached))).close()
        memory = shared_memory.SharedMemory(name=slot.name)
        _attached[slot.name] = memory
    return np.ndarray(slot.shape, np.dtype(slot.dtype), buffer=memory.buf)


def _run_in_child(
    fn: Callable[..., Any], args: tuple[Any, ...], into: FrameSlot | None, out: FrameSlot | None
) -> Any:
    if into is not None:
        frame = _view(into)
        frame.flags.writeable = False  # the caller's frame, as it was handed over
        args = (frame, *args)
    try:
        result = fn(*args)
    except Exception as exc:
        try:
            pickle.loads(pickle.dumps(exc))
        except Exception:  # one that cannot cross would break the pool: its text crosses
            raise RuntimeError(f"{type(exc).__name__}: {exc}") from None
        raise
    if out is None:
        return result
    target = _view(out)
    if not isinstance(result, np.ndarray) or result.shape != target.shape:
        got = getattr(result, "shape", type(result).__name__)
        raise ValueError(f"{fn.__name__} gave {got}, not the frame of {target.shape} promised")
    np.copyto(target, result, casting="unsafe")
    return None


IMAGE_PROCESS = ImageProcess()
atexit.register(IMAGE_PROCESS.close)
