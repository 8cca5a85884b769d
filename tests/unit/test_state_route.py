"""GET /state is the app's own first route, answered by DirectJsonRoute, and the only one."""

from __future__ import annotations

from pathlib import Path

from fastapi.routing import APIRoute

from server.api.direct_json import DirectJsonRoute
from server.api.methods import _http_routes
from server.bootstrap.app import create_app
from server.settings.model import Settings


def test_state_is_tried_first_on_the_apps_own_router(tmp_path: Path) -> None:
    # An included router's routes are matched through a layer of FastAPI's own
    # (the router, then its routes again): the most polled route skips it.
    app = create_app(Settings(data_path=tmp_path))
    routes = app.router.routes
    first = next(route for route in routes if isinstance(route, APIRoute))
    assert isinstance(first, DirectJsonRoute)
    assert (first.path, first.methods) == ("/state", {"GET"})
    included = [i for i, route in enumerate(routes) if hasattr(route, "effective_route_contexts")]
    assert included, "the app includes its routers"
    assert routes.index(first) < min(included)


def test_one_route_answers_get_state(tmp_path: Path) -> None:
    app = create_app(Settings(data_path=tmp_path))
    answering = [
        methods
        for pattern, methods in _http_routes(app.routes)
        if pattern.match("/state") and "GET" in methods
    ]
    assert len(answering) == 1
