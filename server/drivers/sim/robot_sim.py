"""A network simulator of the robot controller: JSON-RPC 2.0 over TCP, JSON lines.

It speaks exactly the protocol of the real controller (see
`server.drivers.jsonlines` for the framing: one JSON object per line, UTF-8,
"\\n"-terminated), so the production client `JsonRpcRobot` is exercised over
a real socket in development and tests.

Controller methods (params by position or by name):
  moveL(pose, speed, acceleration)  linear move of the tool point, mm/s and mm/s²
  moveJ(target, speed)              joint move; the simulator has no kinematics and
                                    moves like moveL (speed taken as mm/s or deg/s,
                                    whichever axis group needs longer)
  getPosition() -> [x, y, z, rx, ry, rz]
  isMoving() -> bool
  stop() -> true                    halts at the current interpolated pose
Motion commands answer `true` as soon as the motion starts. A move sent while
moving replaces the current one from the current interpolated pose. When the
connection of the client that commanded a motion is lost, the motion stops
(as a controller's communication watchdog would). Targets
outside the x/y/z workspace box are refused with error 1001; bad params with
-32602. Malformed JSON gets -32700 (id null) and the connection stays open;
batch requests (arrays) are refused with -32600.

Simulator-only methods, never on a real controller (all prefixed `sim.`, and
answered even while a stall is injected so a test can always clear it):
  sim.getExecutedPath()   the finished or interrupted segments (the last PATH_SIZE)
  sim.clearPath()
  sim.injectFault({"kind": "drop" | "stall" | "fail_next", "duration": s})
      (params by name, or that object as the single positional param)
      drop:      close every client connection (over the wire: just after answering
                 true); with `duration`, connections made in the next `duration` s
                 are accepted and closed at once
      stall:     stop answering every non-`sim.` request (requests are read and
                 discarded, motion carries on) until cleared or for `duration` s
      fail_next: the next moveL/moveJ answers error 1002 and does not move
  sim.clearFaults()
  sim.stats()             method counts, stop count, time of the last stop, clients

In-process only (a test's Python API): `delay_answers(ms)` answers every request `ms`
milliseconds late, as a congested network or a loaded controller would (the cell's
round-trip trend warns of it); `clear_faults()` ends it too.

Motion is computed from elapsed time (no background task): the pose is a
linear interpolation of all six values between start and target, reached after
distance / speed / speed_factor seconds. Acceleration is validated but not
modelled. Run alone with:
  python -m server.drivers.sim.robot_sim --host 127.0.0.1 --port 30003 [--speed-factor F]
      [--workspace-min X Y Z] [--workspace-max X Y Z] [--log-level INFO]
It prints "robot simulator listening on HOST:PORT" once listening (the real
port when --port 0) and exits cleanly on SIGTERM or SIGINT.
"""

from __future__ import annotations

import argparse
import asyncio
import functools
import logging
import math
import time
from collections import Counter, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from server.drivers.base import Pose
from server.drivers.jsonlines import (
    INJECTED_FAILURE,
    INTERNAL_ERROR,
    INVALID_PARAMS,
    INVALID_REQUEST,
    METHOD_NOT_FOUND,
    PARSE_ERROR,
    WORKSPACE_VIOLATION,
    JsonRpcError,
    LineDecoder,
    LineTooLong,
    MalformedLine,
    encode_message,
    make_error,
    make_result,
    parse_request,
)
from server.drivers.sim.standalone import (
    run_standalone,
    serve_until_signalled,
    simulator_arguments,
)

logger = logging.getLogger(__name__)

FAULT_KINDS = ("drop", "stall", "fail_next")
# How long after a move ends as planned the tool still counts as moving for a
# speed-following dispenser: the run's next segment is commanded within it.
BLEND_S = 0.15


def motion_duration(start: Sequence[float], target: Sequence[float], speed: float) -> float:
    """Seconds a move takes at `speed` (before any speed factor).

    The larger of the tool-point distance (mm) and the largest orientation
    change (deg), divided by speed: an orientation-only move still takes time.
    The client uses the same rule to size its move deadline.
    """
    distance = math.dist(start[:3], target[:3])
    turn = max((abs(b - a) for a, b in zip(start[3:], target[3:], strict=True)), default=0.0)
    return max(distance, turn) / speed


# Stretches of motion kept for `motion_between` (a dispenser reads it at least every few
# seconds, a handful of moves apart): enough however long its reads are apart on a busy machine.
MOTION_SPANS = 1024

# Segments the simulator remembers: hundreds of runs of a part (a few to a few hundred moves
# each), enough for any test between two clearPath calls and for the bead of the part on the
# table (camera_bead.py); older ones go, so a cell that runs for days holds no more.
PATH_SIZE = 10_000


@dataclass(frozen=True, slots=True)
class PathSegment:
    """One executed motion: where it started, where it really ended, and how."""

    method: str
    start: Pose
    end: Pose
    speed: float
    interrupted: bool
    t_start: float  # time.time()
    t_end: float

    def to_json(self) -> dict[str, Any]:
        """The wire form returned by sim.getExecutedPath."""
        return {
            "method": self.method,
            "start": list(self.start),
            "end": list(self.end),
            "speed": self.speed,
            "interrupted": self.interrupted,
            "t_start": self.t_start,
            "t_end": self.t_end,
        }


@dataclass
class _Motion:
    """The move under way, interpolated from elapsed monotonic time."""

    method: str
    start: Pose
    target: Pose
    speed: float
    started_mono: float
    started_wall: float
    duration: float

    def fraction(self, now: float) -> float:
        if self.duration <= 0:
            return 1.0
        return min(1.0, max(0.0, (now - self.started_mono) / self.duration))

    def pose_at(self, now: float) -> Pose:
        f = self.fraction(now)
        return Pose(*(a + (b - a) * f for a, b in zip(self.start, self.target, strict=True)))


def _number(value: Any, name: str, *, positive: bool = False) -> float:
    """A finite JSON number (not a boolean), or -32602."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise JsonRpcError(INVALID_PARAMS, f"{name} must be a finite number, got {value!r}")
    if positive and value <= 0:
        raise JsonRpcError(INVALID_PARAMS, f"{name} must be greater than 0, got {value!r}")
    return float(value)


def _pose(value: Any, name: str) -> Pose:
    if not isinstance(value, list) or len(value) != 6:
        raise JsonRpcError(INVALID_PARAMS, f"{name} must be [x, y, z, rx, ry, rz], got {value!r}")
    return Pose(*(_number(v, f"{name}[{i}]") for i, v in enumerate(value)))


Params = list[Any] | dict[str, Any]


def _bind(params: Params, names: Sequence[str]) -> list[Any]:
    """Params by position or by name, in `names` order; exactly these names, or -32602."""
    if isinstance(params, list):
        if len(params) != len(names):
            raise JsonRpcError(
                INVALID_PARAMS,
                f"expected {len(names)} params ({', '.join(names)}), got {len(params)}",
            )
        return list(params)
    missing = [n for n in names if n not in params]
    extra = [k for k in params if k not in names]
    if missing or extra:
        raise JsonRpcError(
            INVALID_PARAMS, f"expected params {list(names)}; missing {missing}, unexpected {extra}"
        )
    return [params[n] for n in names]


def _without_params(action: Callable[[], Any]) -> Callable[[Params], Any]:
    """A handler for a method that takes no params: any given are -32602."""

    def handler(params: Params) -> Any:
        _bind(params, ())
        return action()

    return handler


def _check_fault(kind: Any, duration: float | None) -> None:
    if kind not in FAULT_KINDS:
        raise ValueError(f"fault kind must be one of {FAULT_KINDS}, got {kind!r}")
    if duration is not None and (not math.isfinite(duration) or duration < 0):
        raise ValueError(f"duration must be a finite number >= 0, got {duration!r}")


class RobotSimulator:
    """The simulated controller: one arm, a workspace box, any number of TCP clients."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        workspace_min: Sequence[float] = (100.0, -400.0, -5.0),
        workspace_max: Sequence[float] = (800.0, 400.0, 500.0),
        home: Sequence[float] = (400.0, 0.0, 200.0, 180.0, 0.0, 0.0),
        speed_factor: float = 1.0,
    ) -> None:
        if speed_factor <= 0:
            raise ValueError("speed_factor must be greater than 0")
        self.host = host
        self._requested_port = port
        self.workspace_min = tuple(float(v) for v in workspace_min)
        self.workspace_max = tuple(float(v) for v in workspace_max)
        self.speed_factor = float(speed_factor)
        self._pose = Pose.from_sequence(home)
        self._motion: _Motion | None = None
        self._ended_mono: float | None = None
        # (start, end) on time.monotonic() of each finished move, for motion_between
        self._moved: deque[tuple[float, float]] = deque(maxlen=MOTION_SPANS)
        self._path: deque[PathSegment] = deque(maxlen=PATH_SIZE)  # oldest dropped first
        self._server: asyncio.Server | None = None
        self._clients: dict[asyncio.StreamWriter, asyncio.Task[None] | None] = {}
        self._stalled = False
        self._stall_until: float | None = None
        self._answer_delay_s = 0.0  # delay_answers
        self._refuse_until = 0.0
        self._fail_next = False
        # Like a controller's communication watchdog: motion stops when the link
        # of the client that commanded it is lost.
        self._serving: asyncio.StreamWriter | None = None
        self._motion_owner: asyncio.StreamWriter | None = None
        self.method_counts: Counter[str] = Counter()
        self.stop_received_count = 0
        self.last_stop_at: float | None = None
        self.ignored_while_stalled = 0
        no_params = _without_params
        self._handlers: dict[str, Callable[[Params], Any]] = {
            "moveL": self._rpc_move_linear,
            "moveJ": self._rpc_move_joint,
            "getPosition": no_params(lambda: list(self.position)),
            "isMoving": no_params(lambda: self.is_moving),
            "stop": no_params(self._rpc_stop),
            "sim.getExecutedPath": no_params(lambda: [s.to_json() for s in self.executed_path]),
            "sim.clearPath": no_params(self._rpc_clear_path),
            "sim.injectFault": self._rpc_inject_fault,
            "sim.clearFaults": no_params(self._rpc_clear_faults),
            "sim.stats": no_params(self.stats),
        }

    # --- lifecycle -------------------------------------------------------------

    @property
    def port(self) -> int:
        """The bound port (the real one when constructed with port=0)."""
        if self._server is None or not self._server.sockets:
            return self._requested_port
        return int(self._server.sockets[0].getsockname()[1])

    async def start(self) -> None:
        """Start listening; returns once connections are accepted."""
        self._server = await asyncio.start_server(
            self._serve_client, self.host, self._requested_port
        )
        logger.info("robot simulator listening on %s:%d", self.host, self.port)

    async def stop(self) -> None:
        """Stop listening and close every client connection."""
        if self._server is not None:
            self._server.close()
        tasks = [t for t in self._clients.values() if t is not None]
        self._drop_clients()  # the handlers see EOF and finish on their own
        if tasks:
            _, stragglers = await asyncio.wait(tasks, timeout=1.0)
            for task in stragglers:
                task.cancel()
        if self._server is not None:
            await self._server.wait_closed()
            self._server = None

    async def __aenter__(self) -> RobotSimulator:
        await self.start()
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.stop()

    # --- in-process API for tests --------------------------------------------

    @property
    def position(self) -> Pose:
        """The tool pose now (interpolated during motion)."""
        self._settle()
        if self._motion is not None:
            return self._motion.pose_at(time.monotonic())
        return self._pose

    @property
    def is_moving(self) -> bool:
        """True while a move is under way (what isMoving answers)."""
        self._settle()
        return self._motion is not None

    def speed_fraction(self) -> float:
        """The tool's actual speed now over its commanded one, on the wall clock:
        `speed_factor` during a move (the simulator moves at the commanded speed times
        speed_factor) and for BLEND_S after one ends as planned (a program's next segment
        follows without a stop, as a controller blends waypoints), 0.0 standing still or
        halted. A speed-following dispenser's speed input (GlueSimulator.speed_source):
        an arm made to move faster than commanded gets the glue its bead needs, not a
        fraction of it."""
        if self.is_moving:
            return self.speed_factor
        blended = self._ended_mono is not None and time.monotonic() - self._ended_mono < BLEND_S
        return self.speed_factor if blended else 0.0

    def motion_between(self, since: float, until: float) -> list[tuple[float, float, float]]:
        """The stretches of [since, until] (time.monotonic()) in which the arm moved, as
        (start, end, speed fraction), oldest first. A speed-following dispenser integrates
        its flow over them, so the glue it counts does not depend on how often it is read;
        unlike `speed_fraction()` they leave out the blend after a move, which stands for
        the few milliseconds until the next one is commanded, not for motion: an arm whose
        next move comes late stands still and lays no glue meanwhile."""
        self._settle()
        spans: list[tuple[float, float]] = []
        for start, end in reversed(self._moved):  # newest first: the moves since `since`
            if end <= since:
                break
            spans.append((start, end))
        spans.reverse()
        motion = self._motion
        if motion is not None:
            spans.append((motion.started_mono, motion.started_mono + motion.duration))
        clipped = [(max(start, since), min(end, until)) for start, end in spans]
        return [(start, end, self.speed_factor) for start, end in clipped if end > start]

    @property
    def executed_path(self) -> list[PathSegment]:
        """Finished and interrupted segments, oldest first (the move under way is not in it;
        the last `PATH_SIZE`)."""
        self._settle()
        return list(self._path)

    def path_snapshot(self, since: float = -math.inf) -> list[PathSegment]:
        """The executed path with the move under way cut at now, without settling anything;
        only the segments still moving after `since` (time.time()).

        Safe to call from another thread (the simulated camera renders the bead in one): it
        only copies, while `executed_path` also records a move that has run out of time.
        """
        recent: list[PathSegment] = []
        for segment in reversed(self._path.copy()):  # a copy: the loop may append meanwhile
            if segment.t_end <= since:
                break
            recent.append(segment)
        path = recent[::-1]
        motion = self._motion
        if motion is not None:
            now = time.monotonic()
            elapsed = min(max(now - motion.started_mono, 0.0), motion.duration)
            path.append(
                PathSegment(
                    motion.method,
                    motion.start,
                    motion.pose_at(now),
                    motion.speed,
                    False,
                    motion.started_wall,
                    motion.started_wall + elapsed,
                )
            )
        return path

    @property
    def client_count(self) -> int:
        """Connections open now (a dropped client disappears from the count)."""
        return len(self._clients)

    def clear_path(self) -> None:
        """Forget the executed path, e.g. between the steps of a test."""
        self._path.clear()

    def inject_fault(self, kind: str, *, duration: float | None = None) -> None:
        """Inject "drop", "stall" or "fail_next" (see the module docstring)."""
        _check_fault(kind, duration)
        logger.warning("robot simulator: injecting fault %s (duration %s)", kind, duration)
        if kind == "drop":
            if duration:
                self._refuse_until = time.monotonic() + duration
            self._drop_clients()
        elif kind == "stall":
            self._stalled = True
            self._stall_until = None if duration is None else time.monotonic() + duration
        else:
            self._fail_next = True

    def delay_answers(self, ms: float) -> None:
        """Answer every request `ms` milliseconds late (0 to 60000)."""
        if not 0 <= ms <= 60000:
            raise ValueError(f"answer delay is between 0 and 60000 ms, got {ms}")
        self._answer_delay_s = float(ms) / 1000.0

    def clear_faults(self) -> None:
        """End a stall, a connection-refusal window, a pending fail_next and late answers."""
        self._answer_delay_s = 0.0
        self._stalled = False
        self._stall_until = None
        self._refuse_until = 0.0
        self._fail_next = False

    def stats(self) -> dict[str, Any]:
        """What sim.stats answers: counters a test checks without parsing logs."""
        return {
            "methods": dict(self.method_counts),
            "stop_count": self.stop_received_count,
            "last_stop_at": self.last_stop_at,
            "ignored_while_stalled": self.ignored_while_stalled,
            "clients": self.client_count,
            "stalled": self.stalled,
            "moving": self.is_moving,
        }

    @property
    def stalled(self) -> bool:
        """True while non-`sim.` requests are ignored; a timed stall expires here."""
        if (
            self._stalled
            and self._stall_until is not None
            and time.monotonic() >= self._stall_until
        ):
            self._stalled = False
            self._stall_until = None
        return self._stalled

    # --- motion ----------------------------------------------------------------

    def _settle(self) -> None:
        """Record the current motion as complete once its time has run out."""
        motion = self._motion
        if motion is not None and motion.fraction(time.monotonic()) >= 1.0:
            self._finish(motion, motion.target, False, motion.started_wall + motion.duration)

    def _interrupt(self) -> None:
        """Halt the current motion where it is now and record it as interrupted."""
        self._settle()
        motion = self._motion
        if motion is not None:
            self._finish(motion, motion.pose_at(time.monotonic()), True, time.time())

    def _finish(self, motion: _Motion, end: Pose, interrupted: bool, t_end: float) -> None:
        self._motion = None
        # when it ended as planned (monotonic), for the blend; None after a halt
        self._ended_mono = None if interrupted else motion.started_mono + motion.duration
        moved_until = time.monotonic() if interrupted else motion.started_mono + motion.duration
        self._moved.append((motion.started_mono, moved_until))
        self._pose = end
        self._path.append(
            PathSegment(
                motion.method,
                motion.start,
                end,
                motion.speed,
                interrupted,
                motion.started_wall,
                t_end,
            )
        )

    def _check_workspace(self, pose: Pose) -> None:
        for axis, value, low, high in zip(
            "xyz", pose[:3], self.workspace_min, self.workspace_max, strict=True
        ):
            if value < low:
                raise JsonRpcError(
                    WORKSPACE_VIOLATION,
                    f"target {axis}={value:g} mm is below the workspace minimum {axis}={low:g} mm",
                    {"axis": axis, "value": value, "limit": low, "bound": "min"},
                )
            if value > high:
                raise JsonRpcError(
                    WORKSPACE_VIOLATION,
                    f"target {axis}={value:g} mm is above the workspace maximum {axis}={high:g} mm",
                    {"axis": axis, "value": value, "limit": high, "bound": "max"},
                )

    def _start_motion(self, method: str, target: Pose, speed: float) -> bool:
        self._check_workspace(target)
        if self._fail_next:
            self._fail_next = False
            raise JsonRpcError(INJECTED_FAILURE, f"{method} failed (injected fault)")
        self._interrupt()
        start = self._pose
        self._motion_owner = self._serving
        self._motion = _Motion(
            method,
            start,
            target,
            speed,
            time.monotonic(),
            time.time(),
            motion_duration(start, target, speed) / self.speed_factor,
        )
        self._settle()  # a zero-length move is complete at once
        return True

    # --- RPC handlers ------------------------------------------------------------

    def _rpc_move_linear(self, params: Params) -> bool:
        pose, speed, acceleration = _bind(params, ("pose", "speed", "acceleration"))
        target = _pose(pose, "pose")
        _number(acceleration, "acceleration", positive=True)
        return self._start_motion("moveL", target, _number(speed, "speed", positive=True))

    def _rpc_move_joint(self, params: Params) -> bool:
        target, speed = _bind(params, ("target", "speed"))
        return self._start_motion(
            "moveJ", _pose(target, "target"), _number(speed, "speed", positive=True)
        )

    def _rpc_stop(self) -> bool:
        self._interrupt()
        return True

    def _rpc_clear_path(self) -> bool:
        self.clear_path()
        return True

    def _rpc_clear_faults(self) -> bool:
        self.clear_faults()
        return True

    def _rpc_inject_fault(self, params: Params) -> bool:
        if isinstance(params, list) and len(params) == 1 and isinstance(params[0], dict):
            params = params[0]
        if not isinstance(params, dict) or "kind" not in params:
            raise JsonRpcError(INVALID_PARAMS, 'expected {"kind": ..., "duration": seconds}')
        unexpected = set(params) - {"kind", "duration"}
        if unexpected:
            raise JsonRpcError(INVALID_PARAMS, f"unexpected fault params {sorted(unexpected)}")
        duration = params.get("duration")
        if duration is not None:
            duration = _number(duration, "duration")
        kind = params["kind"]
        try:
            _check_fault(kind, duration)
        except ValueError as exc:
            raise JsonRpcError(INVALID_PARAMS, str(exc)) from None
        if kind == "drop":  # after this answer has been written, so the caller gets it
            asyncio.get_running_loop().call_soon(
                functools.partial(self.inject_fault, kind, duration=duration)
            )
        else:
            self.inject_fault(kind, duration=duration)
        return True

    def handle(self, message: Any) -> dict[str, Any] | None:
        """Answer one decoded message; None when no answer goes out (notification, stall)."""
        if isinstance(message, MalformedLine):
            return make_error(None, PARSE_ERROR, f"parse error: {message.reason}")
        try:
            request = parse_request(message)
        except JsonRpcError as exc:
            request_id = message.get("id") if isinstance(message, dict) else None
            if not isinstance(request_id, int | str) or isinstance(request_id, bool):
                request_id = None
            return make_error(request_id, exc.code, exc.message)
        self.method_counts[request.method] += 1
        if request.method == "stop":
            self.stop_received_count += 1
            self.last_stop_at = time.time()
        if self.stalled and not request.method.startswith("sim."):
            self.ignored_while_stalled += 1
            return None
        handler = self._handlers.get(request.method)
        try:
            if handler is None:
                raise JsonRpcError(METHOD_NOT_FOUND, f"method {request.method!r} not found")
            result = handler(request.params)
        except JsonRpcError as exc:
            response = make_error(request.id, exc.code, exc.message, exc.data)
        except Exception:  # a simulator bug must not kill the connection
            logger.exception("robot simulator: %s failed", request.method)
            response = make_error(request.id, INTERNAL_ERROR, f"{request.method} failed")
        else:
            response = make_result(request.id, result)
        return None if request.is_notification else response

    # --- connections -------------------------------------------------------------

    def _drop_clients(self) -> None:
        for writer in list(self._clients):
            writer.close()

    async def _serve_client(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        if time.monotonic() < self._refuse_until:
            writer.close()
            return
        self._clients[writer] = asyncio.current_task()
        decoder = LineDecoder()
        try:
            while True:
                data = await reader.read(65536)
                if not data:
                    break
                try:
                    messages = decoder.feed(data)
                except LineTooLong as exc:
                    writer.write(encode_message(make_error(None, INVALID_REQUEST, str(exc))))
                    messages = exc.messages
                for message in messages:
                    self._serving = writer
                    response = self.handle(message)
                    self._serving = None
                    if response is not None:
                        if self._answer_delay_s:
                            await asyncio.sleep(self._answer_delay_s)
                        writer.write(encode_message(response))
                await writer.drain()
        except asyncio.CancelledError:
            raise
        except (ConnectionError, OSError) as exc:
            logger.info("robot simulator: client connection ended: %s", exc)
        finally:
            self._clients.pop(writer, None)
            writer.close()
            if self._motion is not None and self._motion_owner is writer:
                logger.warning("robot simulator: commanding client gone; stopping motion")
                self._interrupt()


async def _run(args: argparse.Namespace) -> None:
    simulator = RobotSimulator(
        args.host,
        args.port,
        workspace_min=args.workspace_min,
        workspace_max=args.workspace_max,
        speed_factor=args.speed_factor,
    )
    await simulator.start()
    await serve_until_signalled(simulator, "robot simulator")


def main(argv: Sequence[str] | None = None) -> None:
    """Command-line entry: serve until SIGTERM or SIGINT."""
    parser = simulator_arguments("Robot controller simulator (JSON-RPC over TCP)", 30003)
    parser.add_argument("--speed-factor", type=float, default=1.0, help="motion time divisor")
    parser.add_argument("--workspace-min", type=float, nargs=3, default=(100.0, -400.0, -5.0))
    parser.add_argument("--workspace-max", type=float, nargs=3, default=(800.0, 400.0, 500.0))
    run_standalone(_run, parser, argv)


if __name__ == "__main__":
    main()
