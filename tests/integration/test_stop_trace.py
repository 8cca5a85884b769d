"""The e-stop's path is the one docs/ARCHITECTURE.md traces: at most 8 files, never back up.

A profiler (`sys.setprofile`) notes, during a real POST /estop on the app in process
(its middlewares, the worker, the journal; fake devices), which step files run code,
in the order each is first entered. A step file is one the request could be handed on
through on its way to the worker: every module of one of the app's own middlewares,
the command route's endpoint and its route class, the poster, the cell's command door
(`Cell.command`), and the files the trace names. Helpers a step calls and returns
from (the audit note, the answer's wording, `decide`) and generic utilities (the
queue, the bus, eager tasks, the journal's writer thread) are not steps.

A file of the HTTP transport (`server/api/`) that is not one of those is a step too
when the request is handed on through it: a frame of its code is still running when
a step file is first entered (a wrapper, not a helper that returned). So a check
folded into the app's one middleware as a call that returns is named inside that
step, and one that wraps the rest of the request is a step of its own.

The test fails if a step file the trace does not name is entered (the path grew, or
the trace is stale), if one it names is not (the trace names a file the request does
not cross), if the trace names more than 8 files, or if the files are entered in
another order than the trace's or turn back up a layer (a transport's file first
entered after a file of the core). A request that is not a stop never enters the
stop lane's file.
"""

from __future__ import annotations

import asyncio
import re
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import FrameType
from typing import Any

import httpx
from fastapi.routing import APIRoute

from server.api import commands
from server.bootstrap.app import create_app
from server.bootstrap.cell import Cell
from server.core.worker.devices import CellDevices
from server.settings.model import Settings
from tests.conftest import START, demo_stores
from tests.fakes import FakeCamera, FakeGlue, FakeRobot
from tests.serving import IN_PROCESS_PEER, admin_headers

ROOT = Path(__file__).resolve().parents[2]
ARCHITECTURE = ROOT / "docs" / "ARCHITECTURE.md"
# Files a request is handed on through on its way to the worker, besides the app's
# middlewares and the command route's own class and endpoint (read from the app itself).
POSTING = ("server/core/worker/posting.py",)
# The HTTP transport: a file of it that a request is handed on through is a step.
HTTP = "server/api/"
# The stop lane: only a stop enters it.
STOP_LANE = "server/api/stop_lane.py"
# The cell's command door: a step as `Cell.command` only.
DOOR = "server/bootstrap/cell.py"
# The layer of a step file, highest first: a path never goes back to a higher one.
LAYERS = (("server/api/", 3), ("server/bootstrap/", 2), ("server/core/", 1))


def documented_steps(trace: str) -> list[str]:
    """The files of an ARCHITECTURE.md trace ("## Trace: <trace>"), in the trace's order."""
    text = ARCHITECTURE.read_text(encoding="utf-8")
    section = text.split(f"## Trace: {trace}", 1)[1].split("\n## ", 1)[0]
    files: list[str] = []
    for found in re.finditer(r"^\d+\. `(server/[\w/]+\.py): ", section, re.MULTILINE):
        if found.group(1) not in files:
            files.append(found.group(1))
    assert files, f"ARCHITECTURE.md has its trace of {trace}"
    ranks = [layer_of(step) for step in files]
    assert ranks == sorted(ranks, reverse=True), f"the trace turns back up a layer: {files}"
    return files


def layer_of(path: str) -> int:
    return next(rank for prefix, rank in LAYERS if path.startswith(prefix))


def _relative(filename: str) -> str | None:
    try:
        return Path(filename).resolve().relative_to(ROOT).as_posix()
    except ValueError:
        return None


class Entries:
    """What the profiler saw: each file's first entry, in order, and which were steps."""

    def __init__(self) -> None:
        self.order: dict[str, int] = {}  # watched and HTTP files, by first entry
        self.steps: set[str] = set()  # the watched files entered, and HTTP files handed on through

    def stepped(self) -> list[str]:
        """The step files, in the order each was first entered."""
        return [path for path in self.order if path in self.steps]


def _module_file(module: str) -> str | None:
    return _relative(sys.modules[module].__file__ or "")


@contextmanager
def first_entries(
    watched: set[str], door: Any, tasks: set[asyncio.Task[Any]], halt_code: Any
) -> Iterator[Entries]:
    """The watched files (and `Cell.command`, as "server/bootstrap/cell.py") in the order
    code of theirs first runs, in the request's task, the worker's or the halt's; and the
    HTTP files whose code is still running when one of them is first entered."""
    entries = Entries()
    paths: dict[str, str | None] = {}
    halt_name = halt_code.co_qualname

    def ours() -> bool:
        task = asyncio.current_task()
        if task is None:
            return False
        if task in tasks:
            return True
        # The halt's task: its coroutine (an eager task), or named after it (eager.py's
        # first step, before Python 3.12).
        coro = task.get_coro()
        return getattr(coro, "cr_code", None) is halt_code or task.get_name() == halt_name

    def path_of(code: Any) -> str | None:
        if code.co_filename not in paths:
            paths[code.co_filename] = _relative(code.co_filename)
        return paths[code.co_filename]

    def handed_on_through(frame: FrameType) -> None:
        """The HTTP files with a frame still running below `frame`: steps."""
        below = frame.f_back
        while below is not None:
            path = path_of(below.f_code)
            if path is not None and path.startswith(HTTP):
                entries.steps.add(path)
            below = below.f_back

    def profile(frame: FrameType, event: str, _arg: Any) -> None:
        if event != "call":
            return
        code = frame.f_code
        if code is door:
            path: str | None = DOOR
        else:
            path = path_of(code)
            if path == DOOR:
                return  # the cell's other functions (`started`...) are not its door
        if path is None or not (path in watched or path.startswith(HTTP)):
            return
        if (path in entries.order and path not in watched) or path in entries.steps:
            return
        if not ours():
            return
        entries.order.setdefault(path, len(entries.order))
        if path in watched:
            entries.steps.add(path)
            handed_on_through(frame)

    sys.setprofile(profile)
    try:
        yield entries
    finally:
        sys.setprofile(None)


async def entered_by(settings: Settings, path: str, body: Any, steps: list[str]) -> Entries:
    """What a real POST `path` enters, from its arrival to its 202."""
    demo_stores(settings.data_path)  # the demo part, for POST /start
    cell = Cell(settings, devices=CellDevices(FakeRobot(50), FakeGlue(), FakeCamera()))
    app = create_app(cell=cell)
    middlewares = {
        _module_file(m.cls.__module__)
        for m in app.user_middleware
        if m.cls.__module__.startswith("server.")
    }
    route = next(r for r in commands.router.routes if isinstance(r, APIRoute) and r.path == path)
    route_files = {_module_file(type(route).__module__), _module_file(route.endpoint.__module__)}
    watched = {p for p in middlewares | route_files if p} | set(POSTING) | set(steps)
    watched.add(DOOR)

    async with app.router.lifespan_context(app):
        transport = httpx.ASGITransport(app=app, client=IN_PROCESS_PEER)
        headers = admin_headers(settings.data_path)
        async with httpx.AsyncClient(transport=transport, base_url="http://cell") as client:
            # A first request builds the app's middleware stack (their constructors
            # run then), as a server's lifespan call does before any request.
            assert (await client.get("/state", headers=headers)).status_code == 200
            assert cell.worker is not None and cell.worker._task is not None
            request_task = asyncio.current_task()
            assert request_task is not None
            tasks = {request_task, cell.worker._task}
            halt_code = CellDevices.safe_halt.__code__
            with first_entries(watched, Cell.command.__code__, tasks, halt_code) as entries:
                answer = await client.post(path, json=body, headers=headers)
            assert answer.status_code == 202, answer.text
    return entries


async def test_the_stop_crosses_the_files_its_trace_names_in_order(
    fast_settings: Settings,
) -> None:
    steps = documented_steps("the e-stop")
    assert len(steps) <= 8, steps
    entered = (await entered_by(fast_settings, "/estop", {"reason": "trace"}, steps)).stepped()
    assert entered == steps, f"the stop crossed {entered}; ARCHITECTURE.md's trace names {steps}"


async def test_a_start_crosses_the_files_its_trace_names_in_order(
    fast_settings: Settings,
) -> None:
    steps = documented_steps("POST /start")
    assert len(steps) <= 8, steps
    entries = await entered_by(fast_settings, "/start", START, steps)
    assert STOP_LANE not in entries.order, "a start entered the stop lane's file"
    entered = entries.stepped()
    assert entered == steps, f"the start crossed {entered}; ARCHITECTURE.md's trace names {steps}"
