"""A query route answered without FastAPI's per-request machinery, with the same answer.

Why: GET /state is what every HMI and supervisor polls, and its cost should be
the framework's floor (bench/rest_throughput.py compares it with a bare FastAPI
endpoint). For a route whose endpoint reads nothing but the request, FastAPI
still resolves its (empty) dependencies, wraps the call and the serialization
in its telemetry operations and builds the answer through its generic path:
about a fifth of the request's CPU time (docs/benchmarks.md). `DirectJsonRoute`
calls the endpoint itself and validates and serializes its result with the
route's own response field, as FastAPI's fast path does (`serialize_json` into
a `Response` with `application/json`): the same bytes, status and headers, the
same 500 if the result does not match the model. Routing, the query check
(server/api/declared_query.py), the HTTP door and openapi.json are unchanged.
"""

from __future__ import annotations

import inspect
from typing import Any

from fastapi import Request, Response
from fastapi.datastructures import DefaultPlaceholder
from fastapi.exceptions import ResponseValidationError

from server.api.declared_query import DeclaredQueryRoute, Handler


class DirectJsonRoute(DeclaredQueryRoute):
    """A route whose endpoint takes only the request and returns its response model's content."""

    def answer_handler(self) -> Handler:
        dependant = self.dependant
        reads_more = (
            dependant.path_params,
            dependant.query_params,
            dependant.header_params,
            dependant.cookie_params,
            dependant.body_params,
            dependant.dependencies,
        )
        field = self.response_field
        shaped = (
            self.response_model_include,
            self.response_model_exclude,
            self.response_model_exclude_unset,
            self.response_model_exclude_defaults,
            self.response_model_exclude_none,
            not self.response_model_by_alias,
            self.response_class is not None
            and not isinstance(self.response_class, DefaultPlaceholder),
        )
        if any(reads_more) or any(shaped) or field is None or self.status_code not in (None, 200):
            raise TypeError(f"{self.path}: DirectJsonRoute needs an endpoint of the request alone")
        endpoint = self.endpoint
        if dependant.request_param_name is None or not inspect.iscoroutinefunction(endpoint):
            raise TypeError(f"{self.path}: the endpoint must be async and take the request")
        name = dependant.request_param_name

        async def answer(request: Request) -> Response:
            content: Any = await endpoint(**{name: request})
            value, errors = field.validate(content, {}, loc=("response",))
            if errors:
                raise ResponseValidationError(errors=errors, body=content)
            return Response(content=field.serialize_json(value), media_type="application/json")

        return answer
