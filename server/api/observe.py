"""Watch every HTTP response go out, without a task per request.

Starlette's function middlewares (`@app.middleware("http")`) run the rest of
the app in a task group with memory streams: several extra task hops per
request, paid by every command including the e-stop. This plain ASGI
middleware passes the request straight through and only notes the status
code on its way out; the observers (audit trail, metrics) run once the
response has been sent. It also counts the commands being answered
(server/core/infra/answers_in_flight.py), from arrival to the last byte handed to the socket,
so the plant's interfaces can hold their work until the answer has gone.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from server.core.infra.answers_in_flight import READS, AnswersInFlight

# (scope, status code, seconds from request to the end of the response)
Observer = Callable[[Scope, int, float], None]


class ResponseObservers:
    """ASGI middleware: call each observer after every HTTP response."""

    def __init__(
        self, app: ASGIApp, observers: list[Observer], answers: AnswersInFlight | None = None
    ) -> None:
        self.app = app
        self.observers = observers
        self.answers = answers

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = time.perf_counter()
        status = 500  # if the app fails before it starts a response
        answers = self.answers if scope["method"] not in READS else None
        answering = answers is not None
        ticket = answers.begin() if answers is not None else 0

        async def noting_status(message: Message) -> None:
            nonlocal status, answering
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)
            ended = message["type"] == "http.response.body" and not message.get("more_body")
            if ended and answering and answers is not None:
                answering = False
                answers.end(ticket)  # the answer is on the wire: the plant may hear of it now

        try:
            await self.app(scope, receive, noting_status)
        finally:
            if answering and answers is not None:
                answers.end(ticket)
            seconds = time.perf_counter() - started
            for observe in self.observers:
                observe(scope, status, seconds)
