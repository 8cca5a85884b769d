"""Query parameters a route does not declare are refused (422 naming each), not ignored.

Why: ignored, `/history?sinse=...` would answer every row, as if the filter had
been applied; a script would never learn its typo, and a report would hold more
than it asked for. A request body already refuses unknown fields (`extra="forbid"`); this is
the same rule for the query string, so openapi.json is the whole truth about
what a route reads.

Why a route class and not a dependency or a middleware: the check needs the
route's own parameters (known only after routing), and it must cost nothing on
the hot path: a request without a query string is not looked at, and the set of
names is computed once per route. The command routes
(server/api/commands.py: `CommandRoute`) call the same `QueryCheck` from their
own handler, so a command is handed on through no file of its own for it.

The one exception is the software stop (`x-ignores-unknown-query` in its
operation): a stop is never refused over something it does not read.
"""

from __future__ import annotations

from collections.abc import Callable, Coroutine
from typing import Any

from fastapi import Request, Response
from fastapi.dependencies.models import Dependant
from fastapi.exceptions import RequestValidationError
from fastapi.routing import APIRoute

# In a route's `openapi_extra`: this route answers whatever the query string holds.
IGNORES_UNKNOWN_QUERY = "x-ignores-unknown-query"


def declared_query_names(dependant: Dependant) -> frozenset[str]:
    """Every query parameter a route reads, its dependencies' included."""
    names: set[str] = set()
    pending = [dependant]
    while pending:
        current = pending.pop()
        names.update(field.alias for field in current.query_params)
        pending.extend(current.dependencies)
    return frozenset(names)


Handler = Callable[[Request], Coroutine[Any, Any, Response]]


class QueryCheck:
    """One route's query check: calling it raises the 422 for each parameter the route
    does not declare; a request without a query string is not looked at."""

    __slots__ = ("declared", "takes")

    def __init__(self, dependant: Dependant) -> None:
        self.declared = declared_query_names(dependant)  # computed once per route
        self.takes = ", ".join(sorted(self.declared)) or "no query parameters"

    def __call__(self, request: Request) -> None:
        if not request.scope["query_string"]:
            return
        unknown = [name for name in request.query_params if name not in self.declared]
        if unknown:
            raise RequestValidationError(
                [
                    {
                        "type": "extra_forbidden",
                        "loc": ("query", name),
                        "msg": f"not a parameter of this route (it takes: {self.takes})",
                        "input": request.query_params[name],
                    }
                    for name in unknown
                ]
            )


def query_check_of(route: APIRoute) -> QueryCheck | None:
    """The route's query check; None for a route that answers whatever the query holds."""
    if (route.openapi_extra or {}).get(IGNORES_UNKNOWN_QUERY):
        return None
    return QueryCheck(route.dependant)


class DeclaredQueryRoute(APIRoute):
    """An APIRoute that answers 422 to a query parameter it does not declare."""

    def answer_handler(self) -> Handler:
        """What answers a request once its query is checked: FastAPI's own handler."""
        return super().get_route_handler()

    def get_route_handler(self) -> Handler:
        handler = self.answer_handler()
        check = query_check_of(self)
        if check is None:
            return handler

        async def checked(request: Request) -> Response:
            if request.scope["query_string"]:  # most requests have none: not looked at
                check(request)
            return await handler(request)

        return checked
