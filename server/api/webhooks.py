"""The webhooks' admin routes: what is configured (redacted) and every delivery's outcome.

Admin only (server/security/policy.py): the configuration names the plant's
receivers, and the deliveries show what the cell told them. Neither ever shows a
secret, nor a URL's path or query (server/settings/webhooks.py says why).
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request

from server.api.analytics import table_route
from server.api.declared_query import DeclaredQueryRoute

router = APIRouter(tags=["webhooks"], route_class=DeclaredQueryRoute)


@router.get("/webhooks")
async def get_webhooks(request: Request) -> dict[str, Any]:
    """Each configured webhook (name, scheme://host:port, events, where its secret comes
    from), with its queue (queued, queue_size, in_flight) and its counters (delivered,
    refused, failed, dropped, abandoned, the last outcome); `missed`: bus records the
    notifier lost by falling behind."""
    notifier = getattr(request.app.state, "webhooks", None)  # server/bootstrap/plant.py
    if notifier is None:
        return {"webhooks": [], "missed": 0}
    status: dict[str, Any] = notifier.status()
    return status


router.add_api_route(
    "/webhooks/deliveries",
    table_route(
        "webhook_deliveries",
        "get_webhook_deliveries",
        "Every webhook notice's final outcome, newest first: delivery id (as the receiver "
        "got it), webhook, kind, when it happened, outcome (delivered, refused, failed, "
        "dropped, abandoned), attempts, last status and error, and each attempt (`tries`).",
    ),
    methods=["GET"],
    name="get_webhook_deliveries",
)
