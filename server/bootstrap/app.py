"""The composition root: the cell, the plant interfaces and the HTTP app, built together.

`create_app` builds everything a server runs (the `Cell`, the OPC UA and MQTT
links and the webhooks of `plant.py`, the routes and the HTTP door around them,
the latency machinery of `latency.py`); FastAPI's lifespan then only starts
what it was given, in order, and stops it in reverse.
Everything the cell does is decided by the worker; this module only wires the
routes and maps the core's typed errors to HTTP answers.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import JSONResponse, Response
from starlette.exceptions import HTTPException as StarletteHTTPException

from server.api import (
    access,
    admin,
    analytics,
    audit,
    camera_preview,
    commands,
    diagnostics,
    inspections,
    maintenance,
    markers,
    me,
    methods,
    metrics,
    openapi_doc,
    orders,
    queries,
    recordings,
    reports,
    watch,
    webhooks,
    workpieces,
    ws,
)
from server.api.audit_repeats import AuditRepeats
from server.api.dashboard import mount_dashboard
from server.api.door import HttpDoor, is_stop
from server.api.schemas import RETRY_AFTER_S
from server.bootstrap import latency
from server.bootstrap.cell import Cell
from server.bootstrap.plant import PlantLinks, stop_cell, webhooks_of
from server.commands import answers
from server.common.errors import (
    ChangeNotSaved,
    EventQueueFull,
    JournalUnavailable,
    WorkerStopped,
)
from server.core.infra.answers_in_flight import AnswersInFlight
from server.settings.access import AccessSettings
from server.settings.model import Settings
from server.views.camera_preview import CameraPreview
from server.views.kpi_query import kpis_of

log = logging.getLogger(__name__)


def create_app(
    settings: Settings | None = None, *, cell: Cell | None = None, tune_process: bool = False
) -> FastAPI:
    """Build the cell (unless given), its plant interfaces and the HTTP app around them;
    all of it starts when the server starts serving.

    `tune_process`: the process is the server's own (`python -m server`, a benchmark
    measuring it so), and takes the garbage collector's settings of `latency.py`."""
    settings = settings or (cell.settings if cell else Settings())
    cell = cell or Cell(settings)
    notifier = webhooks_of(cell)  # the webhooks
    gate = access.Access(settings.section(AccessSettings), settings.data_path)
    # The commands being answered: the plant's interfaces hold their work until none is.
    in_flight = AnswersInFlight()
    app: FastAPI
    plant = PlantLinks(
        cell,
        gate.tokens,
        in_flight,
        health=lambda: queries.health_of(app),
        kpis=lambda: kpis_of(cell),
    )

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        try:
            await cell.start()
        except BaseException:
            await notifier.stop()  # its subscription, never started
            raise
        assert cell.journal is not None
        notifier.start(cell.view, cell.journal)
        gate.tokens.ensure_admin()
        app.state.metrics.attach(cell)
        try:
            await plant.start()
        except BaseException:
            await stop_cell(cell, notifier)
            raise
        try:
            yield
        finally:
            await plant.stop()  # `offline` before the cell stops
            await app.state.metrics.detach()
            await app.state.camera_preview.close()
            app.state.audit_repeats.close()  # the counts folded so far, before the journal closes
            await stop_cell(cell, notifier)

    app = FastAPI(
        title="Glue cell control server",
        version="0.1.0",
        summary="One state machine drives a glue-spraying robot cell.",
        lifespan=lifespan,
        # No interactive /docs or /redoc: they load their scripts from a CDN, which a
        # plant network may not reach, and they would be open routes. The description
        # is /openapi.json (viewer) and, for integrators, openapi.json in the repository.
        docs_url=None,
        redoc_url=None,
        generate_unique_id_function=openapi_doc.operation_id_of,
    )
    app.state.cell = cell
    app.state.settings = settings
    app.state.mqtt = plant.mqtt  # the MQTT link (mqtt_url set), for /health and /metrics
    app.state.opcua = plant.opcua  # the OPC UA server (opcua_endpoint set), for /metrics
    app.state.webhooks = notifier  # for GET /webhooks and /metrics
    app.state.ws_hub = ws.WebSocketHub(
        settings.max_broadcast_clients,
        settings.ws_client_buffer,
        per_token=settings.max_broadcast_clients_per_token,
        reserved=settings.broadcast_clients_reserved,
    )
    app.state.access = gate
    app.state.access.revocation_listeners.append(app.state.ws_hub.views.revoke)
    app.state.camera_preview = CameraPreview(cell, settings)
    app.state.access.revocation_listeners.append(app.state.camera_preview.revoke)
    # The most polled route first, then its router: the router tries routes in order.
    queries.add_state_route(app)
    for router in (
        queries.router,
        me.router,
        commands.router,
        workpieces.router,
        orders.router,
        markers.router,
        maintenance.router,
        analytics.router,
        inspections.router,
        recordings.router,
        reports.router,
        metrics.router,
        admin.router,
        diagnostics.router,
        webhooks.router,
        camera_preview.router,
        watch.router,
    ):
        app.include_router(router)
    app.state.metrics = metrics.Metrics(app)
    # HEAD and OPTIONS, once the access check has let them through (each as its route needs).
    app.state.route_methods = methods.RouteMethods(app)
    app.state.answers = in_flight
    # Identical refusals within audit_repeat_window: one audit row with a count.
    app.state.audit_repeats = AuditRepeats(settings.audit_repeat_window, lambda: cell.journal)
    # Every HTTP request's checks before routing, in one middleware (server/api/door.py):
    # the response watched, the access policy (server/security/policy.py), the e-stop
    # made and answered at once (its devices commanded before its body is read, its
    # event ahead of the queue), the body limit, HEAD and OPTIONS.
    app.add_middleware(
        HttpDoor,
        access=app.state.access,
        observers=[
            audit.audit_observer(
                lambda scope: scope["app"].state.cell.journal, app.state.audit_repeats
            ),
            app.state.metrics.observe_response,
        ],
        answers=app.state.answers,
        route_methods=app.state.route_methods,
        max_bytes=settings.max_request_bytes,
    )
    if settings.cors_allowed_origins:
        app.add_middleware(
            CORSMiddleware,
            allow_origins=settings.cors_allowed_origins,
            allow_methods=["GET", "POST", "PUT", "PATCH", "DELETE"],
            allow_headers=["Authorization", "Content-Type"],
            # What a dashboard on another origin needs to read: the camera frame's
            # provenance and how long to wait after a 503.
            expose_headers=["X-Frame-Time", "X-Frame-Source", "X-Frame-Run-Id", "Retry-After"],
        )
    app.include_router(ws.router)
    app.include_router(camera_preview.ws_router)
    mount_dashboard(app)  # the operator dashboard at /, assets under /hmi/
    _install_error_handlers(app)
    # The document says what the app really does: its 422 body and the gate's roles.
    openapi_doc.install(app)
    # Every route prepared before the port opens; the collector tuned when asked.
    latency.install(app, tune_process=tune_process)
    return app


def _install_error_handlers(app: FastAPI) -> None:
    def current_state(request: Request) -> str:
        cell = request.app.state.cell
        return cell.view.state.value if cell.started else "INITIALIZING"

    async def try_again_later(request: Request, exc: Exception) -> JSONResponse:
        """503 for a full event queue, a worker shutting down or a journal that cannot
        write: nothing was changed."""
        request.state.audit_reason = str(exc)  # for the refusal's audit row
        body = {
            "accepted": False,
            "state": current_state(request),
            "message": str(exc),
            "retry_after": RETRY_AFTER_S,
        }
        return JSONResponse(body, status_code=503, headers={"Retry-After": str(RETRY_AFTER_S)})

    app.add_exception_handler(EventQueueFull, try_again_later)
    app.add_exception_handler(405, methods.method_not_allowed)
    app.add_exception_handler(WorkerStopped, try_again_later)
    app.add_exception_handler(JournalUnavailable, try_again_later)

    @app.exception_handler(StarletteHTTPException)
    async def refused(request: Request, exc: StarletteHTTPException) -> Response:
        """The framework's answer, and the reason in the refusal's audit row (it was empty)."""
        if isinstance(exc.detail, str) and not getattr(request.state, "audit_reason", None):
            request.state.audit_reason = exc.detail
        return await http_exception_handler(request, exc)

    @app.exception_handler(ChangeNotSaved)
    async def not_saved(request: Request, exc: ChangeNotSaved) -> JSONResponse:
        """507 (no room) or 503: the change was on record but could not be written; not applied."""
        return JSONResponse({"detail": str(exc)}, status_code=exc.status)

    @app.exception_handler(RequestValidationError)
    async def invalid_request(request: Request, exc: RequestValidationError) -> JSONResponse:
        problems = []
        for error in exc.errors():
            if error["type"] == "json_invalid":  # its loc is ("body", character position)
                at, why = error["loc"][-1], error.get("ctx", {}).get("error", "")
                message = f"not valid JSON at character {at}" + (f": {why}" if why else "")
                problems.append({"field": "body", "message": message, "type": error["type"]})
                continue
            problems.append(answers.problem_of(error))  # as MQTT and OPC UA word it
        body: dict[str, Any] = {"detail": answers.invalid_request(problems), "errors": problems}
        request.state.audit_reason = body["detail"]  # the refusal's audit row says why
        if is_stop(request.scope):
            # A stop is never refused over its body: it is made, and the 422 says so.
            body.update(await commands.stop_anyway(request))
        return JSONResponse(body, status_code=422)
