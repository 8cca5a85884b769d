"""The OPC UA door's stop lane: a session's method calls served side by side, the stop at once.

asyncua reads a connection's requests in order and serves one at a time: it
awaits a Call's methods, sends the answer, and only then reads the next
request. A method of the cell answers once the worker has decided its command
and the decision is on disk (server/opcua/methods.py), so a stop behind a
burst of calls on one session would wait for each of them to be decided and
written. The stop is served ahead of that queue, as HTTP's stop lane serves it
ahead of the HTTP requests (server/api/stop_lane.py).

How: each connection's processor (asyncua's `UaProcessor`, one per connection)
has its `process_message` wrapped when its session is created. A Call request
is decoded there, in order, after asyncua's own steps for every request (the
session and its user, the permission check with the caller's identity and the
size bound, server/opcua/protection.py), then served as a task of its own whose
first step is run at once (server/core/infra/eager.py: `start_task`): the
method's checks, and for a command its submission to the worker, happen in the
order the calls came; a stop's halt frames are written before the next
request is read. Its answer is sent when it is ready: OPC UA matches an answer
to its request by the request handle, not by order. Every other request goes
to asyncua as before.

Only `ADMITTED` calls of the whole server are served at once; the others wait
in the lane's line, in the order they came, and each is started as one ahead
of it finishes. Why: asyncua hands a connection's requests over one after the
other without yielding while they are already read, so a burst of calls was
decoded and started in one turn of the loop, each one's checks and submission
run there and then, and a stop read after the burst waited for that whole
turn (docs/benchmarks.md, "The stop through every door"). Waiting in the line
costs the loop nothing: a call there is a few decoded fields, not a task. A
stop is never in the line: it is started at once, before any call waiting.

As many calls of one connection may wait for their answers at once (in the
line or served) as asyncua lets requests wait on a connection
(`max_pending_messages_per_connection`, 500): what waited in asyncua's queue
before now waits in the line and the worker's queue (bounded too: its refusal
is BadResourceUnavailable, as HTTP's 503). Beyond that a call is answered
BadTooManyOperations at once, never a stop.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
import weakref
from collections import deque
from collections.abc import Awaitable, Callable
from contextvars import ContextVar
from typing import Any, Final

from asyncua import Server, ua
from asyncua.common.utils import ServiceError
from asyncua.ua.ua_binary import nodeid_from_binary, struct_from_binary

from server.commands.catalogue import ADMITTED
from server.core.infra.eager import start_task

log = logging.getLogger(__name__)

_CALL_REQUEST: Final = ua.NodeId(ua.Int32(ua.ObjectIds.CallRequest_Encoding_DefaultBinary))


ProcessMessage = Callable[[Any, Any], Awaitable[bool]]
# The e-stops counted when the call being served was read: `_serve` sets it in the call's
# own task, and the cell's methods (server/opcua/methods.py) hand it to `Cell.command`.
ASKED_AT_ESTOPS: ContextVar[int | None] = ContextVar("asked_at_estops", default=None)
# processor, session, request header, seq, methods, the e-stops counted as it was read
Call = tuple[Any, Any, Any, Any, list[Any], int]


class CallLane:
    """Serves the Call requests of every session of one server, stops first."""

    def __init__(
        self,
        server: Server,
        is_stop: Callable[[ua.NodeId], bool],
        stops_now: Callable[[], int],
    ) -> None:
        self.server = server
        self._is_stop = is_stop  # whether a method node is a stop (the catalogue's `stop`)
        self._stops_now = stops_now  # the cell's e-stops counted so far (`Cell.stops_now`)
        self._limit = server.iserver.max_pending_messages_per_connection
        self._in_flight: weakref.WeakKeyDictionary[Any, set[asyncio.Task[None]]] = (
            weakref.WeakKeyDictionary()
        )
        self._waiting: weakref.WeakKeyDictionary[Any, int] = weakref.WeakKeyDictionary()
        self._line: deque[Call] = deque()  # calls admitted to no service yet, in order
        self._served = 0  # calls (not stops) being served now, at most ADMITTED

    def install(self) -> None:
        """Wrap asyncua's session creation (after `Server.init`): each connection's
        processor is adopted when its session is made."""
        iserver = self.server.iserver
        create = iserver.create_session

        def create_session(*args: Any, **kwargs: Any) -> Any:
            session = create(*args, **kwargs)
            self._adopt_processors()
            return session

        setattr(iserver, "create_session", create_session)  # noqa: B010 (an instance's method)

    async def close(self) -> None:
        """Cancel the calls still waiting for their answers (the server stops)."""
        self._line.clear()
        tasks = [task for tasks in self._in_flight.values() for task in tasks]
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    def _adopt_processors(self) -> None:
        binary = self.server.bserver
        for protocol in list(binary.clients if binary is not None else ()):
            processor = protocol.processor
            if processor is None or processor in self._in_flight:
                continue
            self._in_flight[processor] = set()
            original: ProcessMessage = processor.process_message

            setattr(processor, "process_message", self._wrapped(processor, original))  # noqa: B010

    def _wrapped(self, processor: Any, original: ProcessMessage) -> ProcessMessage:
        """The processor's `process_message`: a Call taken here, anything else asyncua's."""

        async def process_message(seqhdr: Any, body: Any) -> bool:
            if not self._take_call(processor, seqhdr, body):
                return await original(seqhdr, body)
            return True

        return process_message

    def _take_call(self, processor: Any, seqhdr: Any, body: Any) -> bool:
        """Start serving a Call request; False for any other request (asyncua's)."""
        peek = body.copy()
        if nodeid_from_binary(peek) != _CALL_REQUEST or processor.session is None:
            return False
        requesthdr = struct_from_binary(ua.RequestHeader, peek)
        session = processor.session
        try:  # asyncua's own steps for a request of a session (UaProcessor._process_message)
            permissions = processor._connection.security_policy.permissions
            if permissions is not None and not permissions.check_validity(
                session.user, _CALL_REQUEST, peek
            ):
                raise ua.uaerrors.BadUserAccessDenied
        except (ServiceError, ua.uaerrors.UaStatusCodeError) as refused:
            _fault(processor, requesthdr, seqhdr, refused.code)
            return True
        processor.session_last_activity = time.monotonic()
        session.touch()
        params = struct_from_binary(ua.CallParameters, peek)
        methods = params.MethodsToCall or []
        stop = any(self._is_stop(method.MethodId) for method in methods)
        call = (processor, session, requesthdr, seqhdr, methods, self._stops_now())
        if stop:
            self._start(call, stop=True)
            return True
        waiting = len(self._in_flight[processor]) + self._waiting.get(processor, 0)
        if waiting >= self._limit:
            _fault(processor, requesthdr, seqhdr, ua.StatusCodes.BadTooManyOperations)
        elif self._served < ADMITTED:
            self._start(call, stop=False)
        else:
            self._line.append(call)
            self._waiting[processor] = self._waiting.get(processor, 0) + 1
        return True

    @property
    def waiting(self) -> int:
        """Calls in the line, not yet served."""
        return len(self._line)

    def _start(self, call: Call, *, stop: bool) -> None:
        """Serve `call` as a task whose first step runs now: a stop's halt frames are
        written before this returns; a call's checks and submission go in its order."""
        processor = call[0]
        task = start_task(self._serve(*call))
        in_flight = self._in_flight[processor]
        in_flight.add(task)
        task.add_done_callback(in_flight.discard)
        if not stop:
            self._served += 1
            task.add_done_callback(self._next)

    def _next(self, _: asyncio.Task[None]) -> None:
        """A call was served: the first in the line is started in its place."""
        self._served -= 1
        while self._line and self._served < ADMITTED:
            call = self._line.popleft()
            processor = call[0]
            self._waiting[processor] -= 1
            if processor.session is None:  # its session closed while it waited
                continue
            self._start(call, stop=False)

    async def _serve(
        self,
        processor: Any,
        session: Any,
        requesthdr: Any,
        seqhdr: Any,
        methods: list[Any],
        asked_at_estops: int,
    ) -> None:
        """The call's methods, then its answer, as asyncua answers a Call. The methods
        find the e-stops counted when the call was read in `ASKED_AT_ESTOPS` (asyncua
        hands them their own arguments only): one made since refuses them."""
        ASKED_AT_ESTOPS.set(asked_at_estops)  # this task's own context
        try:
            results = await session.call(methods)
        except (ServiceError, ua.uaerrors.UaStatusCodeError) as refused:
            _fault(processor, requesthdr, seqhdr, refused.code)
            return
        except Exception:
            log.exception("OPC UA: a call failed")
            _fault(processor, requesthdr, seqhdr, ua.StatusCodes.BadInternalError)
            return
        response = ua.CallResponse()
        response.Results = results
        with contextlib.suppress(Exception):  # the connection may be gone by now
            processor.send_response(requesthdr.RequestHandle, seqhdr, response)


def _fault(processor: Any, requesthdr: Any, seqhdr: Any, code: int) -> None:
    response = ua.ServiceFault()
    response.ResponseHeader.ServiceResult = ua.StatusCode(ua.UInt32(code))
    with contextlib.suppress(Exception):
        processor.send_response(requesthdr.RequestHandle, seqhdr, response)
