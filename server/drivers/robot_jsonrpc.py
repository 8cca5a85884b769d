"""The production robot client: JSON-RPC 2.0 over one TCP connection, JSON lines.

Framing is that of `server.drivers.jsonlines`: one JSON object per line, UTF-8,
terminated by "\\n". Requests are pipelined: each gets an integer id and a
future in a pending table, and a single reader task resolves futures by id.
Nothing holds a lock across a move, so `stop()` always goes out at once even
while `move_linear` is polling, which is what makes it an emergency stop.

Losing the connection (EOF, reset, write failure) fails every pending call at
once with `DeviceDisconnected`, reports one `COMM_LOST` fault, and starts a
background reconnection with exponential backoff. Calls made while the link is
down fail fast instead of queueing: a queued move replayed seconds later on a
reconnected arm would be dangerous.

`stop()` is the exception, because a stop can never be dangerous: it is written
on whatever socket is open, a new link's still waiting for its connection
probe included, never refused because the link is not confirmed yet. With no
socket at all it fails (the halt reports it) and is owed: the next link sends
it before its connection probe, and each attempt sends it again until one is
answered.

A quiet link is watched too: with `heartbeat_interval` set, a link that has
carried no answer for that long is asked `getPosition`. A controller that stops
answering while the cell is IDLE is then found within interval + timeout, not
at the next move: one `NO_ANSWER` fault per onset, the condition listed in
`health.active_faults` until an answer comes again. Any other request that
times out counts the same way, so a controller known to be silent is never
offered a reset. Every pose read (a move's own, the heartbeat's, the cell's
live feed's) is kept in `health.details["position"]`, with its time in
`position_at`.

Sessions: every new link, and every `new_session()` (a reset's probe calls
it), begins a numbered session. A request belongs to the session it was sent
in; its timeout or its late answer, once a newer session has begun, is only
its caller's business: it reports no fault and changes no health. Without
this, a `getPosition` a stalled controller swallowed before a reset would time
out after the reset had passed and send the cell back to ERROR with a stale
fault.

Motion commands answer as soon as the motion starts, so `move_linear` and
`move_joint` poll `isMoving` until it turns false, then check the arm really
is at the target (another party may have stopped or replaced the move).
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import math
import time
from typing import Any

from server.common.errors import DeviceDisconnected, DeviceError, DeviceTimeout, RobotCommandError
from server.drivers import wear
from server.drivers.base import DeviceFault, DeviceHealth, FaultListener, Pose
from server.drivers.jsonlines import (
    MAX_LINE_BYTES,
    LineDecoder,
    LineTooLong,
    MalformedLine,
    encode_message,
    make_request,
)
from server.drivers.move_timing import expected_move_duration, next_poll_s

logger = logging.getLogger(__name__)

DEVICE = "robot"


class MotionInterrupted(DeviceError):
    """A move ended (isMoving false) away from its target: stopped or replaced by someone else."""

    def __init__(self, method: str, target: Pose, reached: Pose) -> None:
        self.method = method
        self.target = target
        self.reached = reached
        super().__init__(
            DEVICE,
            f"{method} ended at {_fmt(reached)} instead of {_fmt(target)}; "
            "the move was stopped or replaced before it finished",
        )


def _fmt(pose: Pose) -> str:
    return "[" + ", ".join(f"{v:.1f}" for v in pose) + "]"


def _angle_gap(a: float, b: float) -> float:
    """Smallest difference between two angles in degrees (180 and -180 are the same)."""
    return abs((b - a + 180.0) % 360.0 - 180.0)


class JsonRpcRobot:
    """A `Robot` reached over JSON-RPC/TCP at host:port.

    `timeout` (robot_communication_timeout) bounds every exchange and is added
    to the expected duration of a move to form the move's deadline.
    """

    def __init__(
        self,
        host: str,
        port: int,
        *,
        timeout: float = 10.0,
        poll_interval: float = 0.01,
        reconnect_initial_delay: float = 0.1,
        reconnect_max_delay: float = 5.0,
        position_tolerance: float = 0.5,
        max_line_bytes: int = MAX_LINE_BYTES,
        heartbeat_interval: float | None = None,
    ) -> None:
        if timeout <= 0:
            raise ValueError("timeout must be greater than 0")
        self.host = host
        self.port = port
        self.timeout = timeout
        self.poll_interval = poll_interval
        self.reconnect_initial_delay = reconnect_initial_delay
        self.reconnect_max_delay = reconnect_max_delay
        self.position_tolerance = position_tolerance
        self.max_line_bytes = max_line_bytes
        self.heartbeat_interval = heartbeat_interval
        self.health = DeviceHealth(name=DEVICE)
        self.health.details.update(
            address=f"{host}:{port}",
            malformed_lines=0,
            unknown_responses=0,
            late_responses=0,
            connection_losses=0,
            reconnects=0,
        )
        self._listener: FaultListener | None = None
        self._ids = itertools.count(1)
        self._last_id = 0
        self._pending: dict[int, asyncio.Future[dict[str, Any]]] = {}
        self._writer: asyncio.StreamWriter | None = None
        self._reader_task: asyncio.Task[None] | None = None
        self._reconnect_task: asyncio.Task[None] | None = None
        self._background: set[asyncio.Task[Any]] = set()
        self._generation = 0  # bumped per link, so stale signals from an old link are ignored
        self._session = 0  # bumped per link and per reset: see "Sessions" in the module doc
        self._connected = False
        self._closing = False
        self._watch_task: asyncio.Task[None] | None = None
        self._last_answer = 0.0  # monotonic time of the last answer on any link
        self._silent = False  # a NO_ANSWER fault was reported and no answer came since
        self._stop_owed = False  # a stop found no socket: the next link sends it first

    # --- lifecycle -------------------------------------------------------------

    @property
    def connected(self) -> bool:
        return self._connected

    def set_fault_listener(self, listener: FaultListener | None) -> None:
        self._listener = listener

    def new_session(self) -> int:
        """Begin a new session: requests already sent can no longer fault the robot."""
        self._session += 1
        return self._session

    async def connect(self) -> None:
        """Open the link and check the controller answers (getPosition).

        Raises DeviceDisconnected or DeviceTimeout; an initial failure does not
        start background reconnection (the caller decides whether to retry), and
        a failure after a lost link leaves the background reconnection running.
        """
        if self._connected:
            return
        self._closing = False
        retrying = self._reconnect_task is not None and not self._reconnect_task.done()
        await self._cancel_reconnect()  # one link at a time: take over from the retry loop
        try:
            await self._open()
        except (OSError, DeviceError) as exc:
            self.health.record_error(str(exc), connected=False)
            if isinstance(exc, DeviceError):
                raise
            raise DeviceDisconnected(
                DEVICE, f"cannot reach the robot controller at {self.host}:{self.port}: {exc}"
            ) from exc
        finally:
            # A failed attempt during an outage (e.g. a refused reset's probe) must not end
            # the background reconnection it took over from.
            if retrying and not self._connected and not self._closing:
                self._reconnect_task = asyncio.get_running_loop().create_task(
                    self._reconnect_loop(), name="robot-reconnect"
                )

    async def close(self) -> None:
        """Close the link and stop reconnecting; not a fault, never raises."""
        self._closing = True
        await self._cancel_reconnect()
        watch, self._watch_task = self._watch_task, None
        if watch is not None:
            watch.cancel()
            await asyncio.wait({watch})
        self._connected = False
        self.health.connected = False
        self._teardown("the robot link was closed")
        reader_task, self._reader_task = self._reader_task, None
        if reader_task is not None:
            await asyncio.wait({reader_task})  # unlike awaiting it, never swallows our own cancel

    async def _cancel_reconnect(self) -> None:
        task, self._reconnect_task = self._reconnect_task, None
        if task is not None:
            task.cancel()
            await asyncio.wait({task})

    async def _open(self) -> None:
        """Connect, start the reader, and probe; on any failure leave nothing behind."""
        try:
            # asyncio.timeout, not wait_for: on Python 3.11 wait_for can drop a cancel
            # that lands as the connection opens, and leave a link nobody owns.
            async with asyncio.timeout(self.timeout):
                reader, writer = await asyncio.open_connection(self.host, self.port)
        except TimeoutError:
            raise DeviceTimeout(
                DEVICE,
                f"no TCP connection to the robot controller at {self.host}:{self.port} "
                f"within {self.timeout:g} s",
            ) from None
        self._generation += 1
        self._session += 1
        self._writer = writer
        self._reader_task = asyncio.create_task(
            self._read_loop(reader, self._generation), name=f"robot-reader-{self.port}"
        )
        try:
            if self._stop_owed:  # a halt found no link: the arm hears it before anything else
                await self._exchange("stop", None)
                self._stop_owed = False
                logger.warning("robot: sent the stop owed since the link was lost")
            await self._exchange("getPosition", None)
        except BaseException:
            self._teardown("the controller did not answer the connection probe")
            raise
        self._connected = True
        self.health.connected = True
        logger.info("robot: connected to %s:%d", self.host, self.port)
        if self.heartbeat_interval and (self._watch_task is None or self._watch_task.done()):
            self._watch_task = asyncio.create_task(self._watch_loop(), name="robot-heartbeat")

    async def _watch_loop(self) -> None:
        """Ask a quiet link for the position, so silence is found while the cell is idle."""
        interval = self.heartbeat_interval
        assert interval
        while not self._closing:
            await asyncio.sleep(interval)
            if not self._connected or time.monotonic() - self._last_answer < interval:
                continue  # down (reconnection reports itself), or a move's polling proves it
            try:
                await self.get_position()  # the pose read is kept in health.details
            except asyncio.CancelledError:
                raise
            except DeviceError:
                pass  # a timeout or a lost link reports itself; a bad answer fails the next call
            except Exception:  # the watch must outlive anything odd the controller sends
                logger.exception("robot: heartbeat failed")

    def _went_silent(self, detail: str) -> None:
        """Report a controller that stopped answering, once per onset."""
        if self._silent:
            return
        self._silent = True
        message = (
            f"the robot controller at {self.host}:{self.port} stopped answering ({detail}); "
            "check that it is powered and not in a fault or protective stop"
        )
        self.health.active_faults = (f"robot: no answer within {self.timeout:g} s",)
        logger.error("robot: %s", message)
        if self._listener is not None:
            try:
                self._listener(DeviceFault(DEVICE, "NO_ANSWER", message))
            except Exception:
                logger.exception("robot: fault listener failed")

    def _teardown(self, reason: str) -> None:
        """Invalidate the current link: fail pending calls, stop the reader, close the socket."""
        self._generation += 1
        pending, self._pending = self._pending, {}
        for future in pending.values():
            if not future.done():
                future.set_exception(DeviceDisconnected(DEVICE, reason))
        if self._reader_task is not None and self._reader_task is not asyncio.current_task():
            self._reader_task.cancel()
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.close()

    def _link_lost(self, generation: int, reason: str) -> None:
        """React once to the loss of link `generation`; later signals for it are ignored."""
        if generation != self._generation:
            return
        was_connected = self._connected
        self._connected = False
        if was_connected:
            self._teardown(f"lost the link to the robot controller ({reason})")
        else:
            self._teardown(f"the link dropped during the connection probe ({reason})")
        if not was_connected or self._closing:
            return
        self.health.record_error(reason, connected=False)
        self.health.details["connection_losses"] += 1
        message = (
            f"lost the link to the robot controller at {self.host}:{self.port} ({reason}); "
            "reconnecting in the background"
        )
        logger.error("robot: %s", message)
        if self._listener is not None:
            try:
                self._listener(DeviceFault(DEVICE, "COMM_LOST", message))
            except Exception:  # a broken listener must not break the driver
                logger.exception("robot: fault listener failed")
        self._reconnect_task = asyncio.get_running_loop().create_task(
            self._reconnect_loop(), name="robot-reconnect"
        )

    async def _reconnect_loop(self) -> None:
        """Retry with exponential backoff until connected or closed."""
        delay = self.reconnect_initial_delay
        while not self._closing:
            await asyncio.sleep(delay)
            try:
                await self._open()
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # keep retrying whatever went wrong; only close() ends this
                if not isinstance(exc, OSError | DeviceError):
                    logger.exception("robot: unexpected error while reconnecting")
                self.health.record_error(f"reconnect failed: {exc}", connected=False)
                logger.debug("robot: reconnect failed (%s); next try in %.2f s", exc, delay)
                delay = min(delay * 2.0, self.reconnect_max_delay)
            else:
                self.health.details["reconnects"] += 1
                logger.warning("robot: reconnected to %s:%d", self.host, self.port)
                return

    async def _read_loop(self, reader: asyncio.StreamReader, generation: int) -> None:
        """Dispatch every response of one link to its pending future by id."""
        decoder = LineDecoder(self.max_line_bytes)
        reason = "the controller closed the connection"
        try:
            while True:
                data = await reader.read(65536)
                if not data:
                    break
                try:
                    messages = decoder.feed(data)
                except LineTooLong as exc:
                    self.health.details["malformed_lines"] += 1
                    logger.warning("robot: ignored an overlong line: %s", exc)
                    messages = exc.messages
                for message in messages:
                    self._dispatch(message)
        except asyncio.CancelledError:
            raise
        except (ConnectionError, OSError) as exc:
            reason = f"connection error: {exc!r}"
        self._link_lost(generation, reason)

    def _dispatch(self, message: Any) -> None:
        if isinstance(message, MalformedLine):
            self.health.details["malformed_lines"] += 1
            logger.warning(
                "robot: ignored a malformed line (%s): %r", message.reason, message.raw[:200]
            )
            return
        raw_id = message.get("id") if isinstance(message, dict) else None
        request_id = raw_id if isinstance(raw_id, int) and not isinstance(raw_id, bool) else None
        future = self._pending.get(request_id) if request_id is not None else None
        if future is None:
            late = request_id is not None and 0 < request_id <= self._last_id
            key = "late_responses" if late else "unknown_responses"
            self.health.details[key] += 1
            log = logger.debug if late else logger.warning
            log("robot: ignored a response with %s id %r: %.200r", key[:-10], raw_id, message)
            return
        if not future.done():
            future.set_result(message)

    # --- exchanges ---------------------------------------------------------------

    async def call(
        self,
        method: str,
        params: list[Any] | dict[str, Any] | None = None,
        *,
        timeout: float | None = None,
    ) -> Any:
        """One request/response; fails fast with DeviceDisconnected while the link is down.

        Public so tools and tests can reach extra methods (e.g. the simulator's `sim.*`).
        """
        if not self._connected:
            raise DeviceDisconnected(
                DEVICE,
                f"{method}: not connected to the robot controller at {self.host}:{self.port}",
            )
        return await self._exchange(method, params, timeout=timeout)

    async def _exchange(
        self,
        method: str,
        params: list[Any] | dict[str, Any] | None,
        *,
        timeout: float | None = None,
    ) -> Any:
        writer = self._writer
        if writer is None:
            raise DeviceDisconnected(DEVICE, f"{method}: no link to the robot controller")
        timeout = self.timeout if timeout is None else timeout
        generation, session = self._generation, self._session
        request_id = next(self._ids)
        self._last_id = request_id
        future: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
        self._pending[request_id] = future
        started = time.monotonic()
        try:
            async with asyncio.timeout(timeout):
                writer.write(encode_message(make_request(method, params, request_id)))
                await writer.drain()
                response = await future
        except TimeoutError:
            message = f"{method} got no answer within {timeout:g} s"
            if session == self._session:
                self.health.record_error(message)
                if self._connected:  # a failed connection probe is its caller's to report
                    self._went_silent(message)
            else:
                logger.info("robot: %s (sent before a reset; not a fault now)", message)
            raise DeviceTimeout(DEVICE, message) from None
        except (ConnectionError, OSError) as exc:
            self._link_lost(generation, f"write failed: {exc!r}")
            raise DeviceDisconnected(DEVICE, f"{method}: write failed: {exc}") from exc
        finally:
            self._pending.pop(request_id, None)
            if future.done() and not future.cancelled():
                # A teardown during this call (the failed write's own, or the reader's)
                # failed the future too; this call has raised already, so that
                # exception is retrieved here rather than logged as never retrieved.
                future.exception()
        self._last_answer = time.monotonic()
        if session == self._session:  # a late answer of an older session proves nothing now
            self.health.record_ok(self._last_answer - started)
            self.health.connected = self._connected
            if self._silent:  # answering again: the condition is gone (a reset may now pass)
                self._silent = False
                self.health.active_faults = ()
                logger.warning("robot: the controller answers again")
        error = response.get("error")
        if error is not None:
            code = error.get("code", 0) if isinstance(error, dict) else 0
            text = str(error.get("message", error)) if isinstance(error, dict) else str(error)
            failure = RobotCommandError(code if isinstance(code, int) else 0, text, method)
            self.health.last_error = str(failure)
            raise failure
        if "result" not in response:
            raise DeviceError(DEVICE, f"{method}: the answer has neither result nor error")
        return response["result"]

    # --- Robot protocol ------------------------------------------------------------

    async def get_position(self) -> Pose:
        """The tool pose now; every pose read is also kept in `health.details` with its time."""
        result = await self.call("getPosition")
        try:
            pose = Pose.from_sequence(result)
        except (TypeError, ValueError) as exc:
            raise DeviceError(
                DEVICE, f"getPosition answered {result!r}, not a pose: {exc}"
            ) from exc
        details = self.health.details
        wear.add(details, wear.TRAVEL_M, wear.travel_m(details.get("position"), pose))
        details.update(position=[round(v, 3) for v in pose], position_at=time.time())
        return pose

    async def is_moving(self) -> bool:
        result = await self.call("isMoving")
        if not isinstance(result, bool):
            raise DeviceError(DEVICE, f"isMoving answered {result!r}, not true/false")
        return result

    async def stop(self) -> None:
        """Stop the arm: written on any open socket, even one whose probe has not answered.

        With no socket at all, DeviceDisconnected, and the stop is owed to the next link.
        """
        if self._writer is None:
            self._stop_owed = True
            raise DeviceDisconnected(
                DEVICE,
                f"stop: no link to the robot controller at {self.host}:{self.port}; "
                "it is sent first when the link is back",
            )
        try:
            await self._exchange("stop", None)
        except DeviceDisconnected:  # the link died under it: owed all the same
            self._stop_owed = True
            raise

    async def move_linear(self, pose: Pose, speed: float, acceleration: float) -> None:
        target = _checked_pose(pose)
        _check_positive(speed, "speed")
        _check_positive(acceleration, "acceleration")
        await self._move("moveL", [list(target), speed, acceleration], target, speed)

    async def move_joint(self, target: Pose, speed: float) -> None:
        checked = _checked_pose(target)
        _check_positive(speed, "speed")
        await self._move("moveJ", [list(checked), speed], checked, speed)

    async def _move(self, method: str, params: list[Any], target: Pose, speed: float) -> None:
        """Start a move, poll isMoving until done, check the arm arrived.

        Deadline: expected duration (distance / speed) + timeout. Cancellation
        sends a shielded stop before re-raising, so the arm never keeps going
        for a caller that gave up. The polls are placed by the move's expected
        end (`server/drivers/move_timing.py`).
        """
        began = time.monotonic()
        try:
            start = await self.get_position()
            loop = asyncio.get_running_loop()
            duration = expected_move_duration(start, target, speed)
            deadline = loop.time() + duration + self.timeout
            await self.call(method, params)
            expected_end = loop.time() + duration  # the arm started before it answered
            while True:
                remaining = deadline - loop.time()
                if remaining <= 0:
                    await self._best_effort_stop(f"{method} overran its deadline")
                    raise DeviceTimeout(
                        DEVICE,
                        f"{method} still moving after its expected duration + {self.timeout:g} s",
                    )
                if not await self.is_moving():
                    break
                await asyncio.sleep(next_poll_s(expected_end - loop.time(), self.poll_interval))
            reached = await self.get_position()
        except asyncio.CancelledError:
            stopping = asyncio.ensure_future(self._best_effort_stop(f"{method} was cancelled"))
            self._background.add(stopping)
            stopping.add_done_callback(self._background.discard)
            with contextlib.suppress(asyncio.CancelledError):
                await asyncio.shield(stopping)
            raise
        finally:
            wear.add(self.health.details, wear.MOTION_S, time.monotonic() - began)
        if not self._arrived(reached, target):
            raise MotionInterrupted(method, target, reached)

    def _arrived(self, reached: Pose, target: Pose) -> bool:
        tolerance = self.position_tolerance
        return math.dist(reached[:3], target[:3]) <= tolerance and all(
            _angle_gap(a, b) <= tolerance for a, b in zip(reached[3:], target[3:], strict=True)
        )

    async def _best_effort_stop(self, why: str) -> None:
        """Send stop, bounded by the timeout; failures are logged, never raised."""
        try:
            await self.stop()
            logger.warning("robot: stop sent because %s", why)
        except asyncio.CancelledError:
            raise
        except DeviceError as exc:
            logger.error("robot: could not send stop after %s: %s", why, exc)


def _checked_pose(pose: Pose) -> Pose:
    checked = Pose.from_sequence(pose)
    if not all(math.isfinite(v) for v in checked):
        raise ValueError(f"a pose must be finite, got {checked}")
    return checked


def _check_positive(value: float, name: str) -> None:
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a finite number greater than 0, got {value!r}")
