"""Process settings for a server that must answer fast, applied by `python -m server`.

- Garbage collection: its thresholds and the freezes `python -m server`
  applies are the e-stop's latency machinery (server/bootstrap/latency.py);
  here, a collection deferred while a stop's frames are written
  (`collection_deferred`).
- Open files: the soft limit is raised to the hard limit, because every
  WebSocket client is a socket and the usual soft limit (1024) is below what
  max_broadcast_clients allows.
- The image process (`server/vision/process.py`) is ended by the app's
  shutdown, not at exit: uvicorn raises SIGTERM or SIGINT again once it has
  shut down, and exit handlers do not run then.
- Background threads (the journal's writer, the state snapshot's) hold back
  while an e-stop's device frames are written (`background_held`). Woken to
  write, such a thread preempts the event loop on a shared core in the
  middle of a stop, between its two frames: behind a full queue the robot's
  frame would wait up to a millisecond for the journal's commit. For those few
  hundred microseconds they are bulk work for the kernel (Linux SCHED_BATCH:
  a wake-up never preempts a running thread), then ordinary threads again.
  Not for longer: as bulk work all the time the writer waits a time slice
  at each wake-up, and every answer behind a busy loop (1000 WebSocket
  clients, vision) takes twice as long.
- Memory arenas (glibc): at most two. By default each thread that allocates
  may get an arena of its own, and the vision threads' 6 MB frames, freed,
  stay in them: a 3-minute soak grows 80 MB that way with no leak (2 MB with
  two arenas). Elsewhere than glibc this does nothing.
- Large blocks (128 KiB and more: frames, images, their crops, journal pages
  in bulk) are mapped on their own and given back to the kernel the moment
  they are freed. glibc otherwise raises that threshold each time such a block
  is freed, up to 32 MiB, after which frames come from the heap, and the heap
  keeps what they leave: the image process held about 200 MB more than it used
  that way. Below 1 MiB the blocks still came from the heaps, where a small
  block freed later pinned the space of many: after 100 runs the image process
  held 18 MB less with the threshold at 128 KiB than at 1 MiB. A mapping costs
  a system call and its pages' first touch, microseconds for such a block.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import gc
import logging
import os
import resource
import threading
from collections.abc import AsyncIterator, Callable, Iterator
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from starlette.applications import Starlette

log = logging.getLogger(__name__)


M_ARENA_MAX = -8  # glibc's mallopt parameter numbers
M_MMAP_THRESHOLD = -3
MALLOC_ARENAS = 2
MMAP_THRESHOLD = 1 << 17  # blocks this large are mapped apart and unmapped when freed


def limit_malloc_arenas() -> bool:
    """Cap glibc's malloc arenas and fix its mmap threshold (see the module docstring);
    False where not glibc."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
        mallopt = libc.mallopt if libc is not None else None
    except (OSError, AttributeError):
        return False
    if mallopt is None or mallopt(M_ARENA_MAX, MALLOC_ARENAS) != 1:
        return False
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD) == 1)


def raise_open_file_limit() -> int:
    """Raise the soft RLIMIT_NOFILE to the hard limit; the limit now in force."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard == resource.RLIM_INFINITY or soft < hard:
        target = hard if hard != resource.RLIM_INFINITY else max(soft, 65536)
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
            soft = target
        except (ValueError, OSError) as exc:
            log.warning("could not raise the open-file limit from %d: %s", soft, exc)
    return soft


_BACKGROUND: set[int] = set()  # native ids of the live threads in `background_thread` blocks
_BATCH = getattr(os, "SCHED_BATCH", None)  # Linux only; elsewhere nothing is held back


@contextlib.contextmanager
def background_thread() -> Iterator[None]:
    """Run the block (a background thread's whole life) as a thread `background_held` holds."""
    native_id = threading.get_native_id()
    _BACKGROUND.add(native_id)
    try:
        yield
    finally:
        _BACKGROUND.discard(native_id)  # never touch an id a later thread may be given


@contextlib.contextmanager
def background_held() -> Iterator[None]:
    """Inside the block no background thread's wake-up preempts the running thread.

    Short blocks only: an e-stop's frames (see the module docstring). Two system
    calls per background thread, neither of which lets the interpreter go.
    """
    if _BATCH is None:
        yield
        return
    param = os.sched_param(0)
    held: list[int] = []
    for native_id in tuple(_BACKGROUND):
        with contextlib.suppress(OSError):  # the thread ended meanwhile
            os.sched_setscheduler(native_id, _BATCH, param)
            held.append(native_id)
    try:
        yield
    finally:
        for native_id in held:
            with contextlib.suppress(OSError):
                os.sched_setscheduler(native_id, os.SCHED_OTHER, param)


@contextlib.contextmanager
def collection_deferred() -> Iterator[None]:
    """No garbage collection starts inside the block; one that falls due runs after it.

    Why: with a young generation of 10 000 objects a collection takes 1.5 to 2 ms,
    and one that starts while an e-stop's frames are being written holds them
    back that long (bench.estop_latency). The block must be short and
    never wait: it is the few hundred microseconds between the stop's arrival and
    its frames on their sockets.
    """
    if not gc.isenabled():
        yield
        return
    gc.disable()
    try:
        yield
    finally:
        gc.enable()


def close_on_shutdown(app: Starlette, close: Callable[[], None]) -> None:
    """`close` run with the app's shutdown (`python -m server` ends the image process so).

    Why here and not at exit: uvicorn, once it has shut down on SIGTERM or Ctrl-C,
    raises the signal again, and the process ends without running its exit
    handlers; the image process (`server/vision/process.py`) and its shared memory
    would be left to the resource tracker, which warns of them as leaked."""
    running = app.router.lifespan_context

    @contextlib.asynccontextmanager
    async def lifespan(app: Any) -> AsyncIterator[Any]:
        try:
            async with running(app) as state:
                yield state
        finally:
            close()

    app.router.lifespan_context = lifespan
