"""GET /diagnostics: the diagnostic bundle of the running server (server/diagnostics/bundle.py)."""

from __future__ import annotations

import asyncio
import time

from fastapi import APIRouter, Request, Response

from server.api.queries import health_of
from server.diagnostics.bundle import archive, collect

router = APIRouter()


@router.get(
    "/diagnostics",
    response_class=Response,
    responses={
        200: {
            "content": {"application/gzip": {"schema": {"type": "string", "format": "binary"}}},
            "description": "a .tar.gz: version, settings (secrets masked), /health, the newest "
            "faults with their context and stack, transitions, the journal's check, the log's end",
        }
    },
)
async def get_diagnostics(request: Request) -> Response:
    """One archive with what a support engineer asks for first (maintenance role).

    Built off the event loop: the journal check reads every recent commit again.
    """
    settings = request.app.state.settings
    health = health_of(request.app)
    files = await asyncio.to_thread(collect, settings, health, "GET /diagnostics")
    name = time.strftime("glue-cell-diagnostics-%Y%m%d-%H%M%S")
    body = await asyncio.to_thread(archive, files, name)
    return Response(
        body,
        media_type="application/gzip",
        headers={"Content-Disposition": f'attachment; filename="{name}.tar.gz"'},
    )
