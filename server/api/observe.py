"""Watch every HTTP response go out, without a task per request.

Starlette's function middlewares (`@app.middleware("http")`) run the rest of
the app in a task group with memory streams: several extra task hops per
request, paid by every command including the e-stop. The HTTP door
(server/api/door.py) instead gives each request a `ResponseWatch`: its `send`
notes the status code on the way out, and `finish` runs the observers (audit
trail, metrics) once the response has been sent. It also counts the commands
being answered (server/core/infra/answers_in_flight.py), from arrival to the last
byte handed to the socket, so the plant's interfaces can hold their work until
the answer has gone.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from starlette.types import Message, Scope, Send

from server.core.infra.answers_in_flight import READS, AnswersInFlight

# (scope, status code, seconds from request to the end of the response)
Observer = Callable[[Scope, int, float], None]


class ResponseWatch:
    """One HTTP request's response, watched from its arrival to its last byte.

    `send` stands in for the server's send; `finish` (always called, the response
    sent or not) ends the answer's count if the last byte never went and calls each
    observer with the status (500 if the app failed before it started a response).
    """

    __slots__ = ("_answers", "_send", "_started", "_ticket", "status")

    def __init__(self, scope: Scope, send: Send, answers: AnswersInFlight | None) -> None:
        self._started = time.perf_counter()
        self.status = 500
        self._send = send
        # A command is counted in flight until its answer is on the wire; a read is not.
        self._answers = answers if scope["method"] not in READS else None
        self._ticket = self._answers.begin() if self._answers is not None else 0

    async def send(self, message: Message) -> None:
        if message["type"] == "http.response.start":
            self.status = message["status"]
        await self._send(message)
        if (
            self._answers is not None
            and message["type"] == "http.response.body"
            and not message.get("more_body")
        ):
            self._end_answer()  # the answer is on the wire: the plant may hear of it now

    def finish(self, scope: Scope, observers: list[Observer]) -> None:
        if self._answers is not None:
            self._end_answer()
        seconds = time.perf_counter() - self._started
        for observe in observers:
            observe(scope, self.status, seconds)

    def _end_answer(self) -> None:
        answers, self._answers = self._answers, None
        if answers is not None:
            answers.end(self._ticket)
