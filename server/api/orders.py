"""Production orders over HTTP: create, list, read, close, resume, and the report.

Each change is committed with its audit row before it is answered (503 if the
journal cannot write, nothing changed). A refusal names why: 404 no such
order, 409 not now (with the cell's or the order's state), 422 naming the field.
The order book itself is `server/orders/book.py`.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Header, Path, Query, Request
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, Field, create_model

from server.api import audit
from server.api.declared_query import DeclaredQueryRoute
from server.api.schemas import ErrorView, Strict, text_body
from server.bootstrap.cell import Cell
from server.common.errors import JournalUnavailable
from server.common.values import whole_number
from server.orders.book import OrderBook, OrderRefused
from server.orders.model import Order
from server.orders.report import report_csv, report_of
from server.security.tokens import Principal
from server.storage.journal import PART_FIGURES
from server.storage.workpieces import IDENTIFIER

router = APIRouter(tags=["orders"], route_class=DeclaredQueryRoute)
ORDER_ID = r"^ord-[0-9a-f]{8}$"
OrderId = Annotated[str, Path(pattern=ORDER_ID, description="the order's id, e.g. ord-1a2b3c4d")]
MAX_QUANTITY = 100_000
IDEMPOTENCY_KEY = r"^[\x21-\x7e]{1,200}$"  # printable ASCII, no spaces
REFUSALS: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorView, "description": "no such order"},
    409: {"model": ErrorView, "description": "not now: the order's or the cell's state says why"},
    503: {"model": ErrorView, "description": "the journal cannot write: nothing was changed"},
}


class OrderRequest(Strict):
    """Body of POST /orders."""

    workpiece_id: str = Field(pattern=IDENTIFIER, description="the library workpiece to make")
    quantity: whole_number(Field(ge=1, le=MAX_QUANTITY)) = Field(  # type: ignore[valid-type]
        description="how many parts the order makes, good or not inspected"
    )


class OrderView(BaseModel):
    order_id: str
    workpiece_id: str
    quantity: int
    defect_limit: int = Field(description="defective parts in a row that stop it (a setting)")
    state: Literal["queued", "running", "held", "completed", "closed"]
    reason: str | None = Field(description="why it is held, closed or completed")
    good: int = Field(description="parts inspected and judged good")
    defective: int = Field(
        description="parts judged defective, or whose run did not complete (not inspected)"
    )
    not_inspected: int = Field(description="parts sprayed whole that nobody inspected")
    counted: int = Field(
        description="parts toward the quantity: good and not inspected (nothing found them wrong)"
    )
    defects_in_row: int
    parts_made: int
    created_at: float
    created_by: str
    updated_at: float


class OrderAnswer(BaseModel):
    order: OrderView
    run_id: str | None = Field(
        None, description="the run of the part just started (None: queued, or the start held it)"
    )


class OrderList(BaseModel):
    orders: list[OrderView]
    active: str | None = Field(description="the id of the order the cell works through")


class _PartOutcome(BaseModel):
    part: int
    run_id: str
    started_at: float | None
    ended_at: float
    outcome: str = Field(
        description="how the run ended: completed, failed, cancelled or interrupted"
    )
    verdict: Literal["good", "defective", "not_inspected"]
    inspected: bool
    reasons: list[str]


# A part of the report: its outcome, then its inspection figures (the journal's
# PART_FIGURES), each a number or None.
PartView = create_model(
    "PartView",
    __base__=_PartOutcome,
    **{name: (float | None, ...) for name in PART_FIGURES},  # type: ignore[call-overload]
)


class OrderReport(BaseModel):
    order: OrderView
    glue_ml_total: float | None
    parts: list[PartView]


def _book(request: Request) -> OrderBook:
    cell: Cell = request.app.state.cell
    assert cell.orders is not None, "the cell is not started"
    return cell.orders


def _who(request: Request) -> str:
    principal: Principal | None = getattr(request.state, "principal", None)
    return principal.name if principal else "anonymous"


def _view(order: Order) -> OrderView:
    return OrderView(**order.as_dict())


def _refused(request: Request, refused: OrderRefused) -> JSONResponse:
    request.state.audit_reason = refused.message
    if refused.status == 422 and refused.field:
        problem = {"field": refused.field, "message": refused.message, "type": "precondition"}
        detail = f"invalid request: {refused.field}: {refused.message}"
        return JSONResponse({"detail": detail, "errors": [problem]}, status_code=422)
    body: dict[str, Any] = {"detail": refused.message}
    if refused.field:  # what the request must change (a 409 on a value the cell lacks)
        body = {"detail": f"{refused.field}: {refused.message}", "field": refused.field}
    return JSONResponse(body, status_code=refused.status)


def _audit(request: Request, detail: str) -> Any:
    request.state.audited = True  # committed with the change, before the answer
    return audit.row(request.scope, "accepted", detail)


async def _durably(work: Any) -> Any:
    try:
        return await work
    except OrderRefused:
        raise
    except Exception as exc:  # the journal's write failed: nothing was changed
        raise JournalUnavailable(str(exc)) from exc


@router.post(
    "/orders",
    status_code=201,
    response_model=OrderAnswer,
    responses={
        **REFUSALS,
        200: {"model": OrderAnswer, "description": "a retry: the order this key made"},
        422: {"description": "a field is wrong, and it is named"},
    },
)
async def create_order(
    request: Request,
    body: OrderRequest,
    idempotency_key: Annotated[
        str | None,
        Header(
            pattern=IDEMPOTENCY_KEY,
            description="any string the client chooses per order (a UUID): a retry with the "
            "same key (the answer was lost) gets the order it made, 200, not a second one",
        ),
    ] = None,
) -> Any:
    """A production order: `quantity` good parts of `workpiece_id`.

    With no order active it runs at once (409 if the cell cannot start a part now:
    nothing is created), else it is queued behind the active one. A workpiece the
    library lacks is a 409 naming `workpiece_id`, as for POST /start. With an
    `Idempotency-Key` already used by this token: 200 and that order as it stands now
    (a 422 naming the header if that order was for another workpiece or quantity).
    """
    book = _book(request)
    if idempotency_key is not None:
        made = book.made_with(idempotency_key, _who(request))
        if made is not None:
            return _replayed(request, made, body)
    detail = f"order {body.quantity} x {body.workpiece_id}"
    try:
        order, run_id = await _durably(
            book.create(
                body.workpiece_id,
                body.quantity,
                _who(request),
                _audit(request, detail),
                idempotency_key,
            )
        )
    except OrderRefused as refused:
        request.state.audited = False
        return _refused(request, refused)
    answer = OrderAnswer(order=_view(order), run_id=run_id)
    return JSONResponse(answer.model_dump(), status_code=201)


def _replayed(request: Request, made: Order, body: OrderRequest) -> JSONResponse:
    """The answer to a retry: the order the key made, or a 422 if the body differs."""
    if (made.workpiece_id, made.quantity) != (body.workpiece_id, body.quantity):
        return _refused(
            request,
            OrderRefused(
                422,
                f"this key made order {made.order_id} ({made.quantity} x {made.workpiece_id}); "
                "a new order needs a new key",
                "Idempotency-Key",
            ),
        )
    request.state.audit_reason = f"retry of order {made.order_id}: nothing new made"
    return JSONResponse(OrderAnswer(order=_view(made)).model_dump(), status_code=200)


@router.get("/orders", response_model=OrderList)
async def list_orders(
    request: Request,
    state: Annotated[
        Literal["queued", "running", "held", "completed", "closed"] | None,
        Query(description="only the orders in this state"),
    ] = None,
) -> OrderList:
    """The orders, newest first, and which one is active."""
    book = _book(request)
    active = book.active
    return OrderList(
        orders=[_view(o) for o in book.listed(state)],
        active=active.order_id if active else None,
    )


@router.get("/orders/{order_id}", response_model=OrderView, responses={404: REFUSALS[404]})
async def get_order(request: Request, order_id: OrderId) -> Any:
    """One order: its state, why, and its counts."""
    try:
        return _view(_book(request).get(order_id))
    except OrderRefused as refused:
        return _refused(request, refused)


@router.post("/orders/{order_id}/close", response_model=OrderView, responses=REFUSALS)
async def close_order(request: Request, order_id: OrderId) -> Any:
    """End an order before its quantity (a run under way goes on: POST /cancel stops it)."""
    try:
        order = await _durably(
            _book(request).close(order_id, _who(request), _audit(request, f"close {order_id}"))
        )
    except OrderRefused as refused:
        request.state.audited = False
        return _refused(request, refused)
    return _view(order)


@router.post("/orders/{order_id}/resume", response_model=OrderAnswer, responses=REFUSALS)
async def resume_order(request: Request, order_id: OrderId) -> Any:
    """Continue a held order (the cell in IDLE: reset it first after a stop)."""
    try:
        order, run_id = await _durably(
            _book(request).resume(order_id, _audit(request, f"resume {order_id}"))
        )
    except OrderRefused as refused:
        request.state.audited = False
        return _refused(request, refused)
    return OrderAnswer(order=_view(order), run_id=run_id)


@router.get(
    "/orders/{order_id}/report",
    response_model=OrderReport,
    responses={
        200: {"content": text_body("text/csv"), "description": "JSON, or CSV with format=csv"},
        404: REFUSALS[404],
    },
)
async def order_report(
    request: Request,
    order_id: OrderId,
    format: Annotated[Literal["json", "csv"], Query(description="json (default) or csv")] = "json",
) -> Any:
    """Every part of the order: run id, times, verdict, precision, glue used, reasons."""
    try:
        order = _book(request).get(order_id)
    except OrderRefused as refused:
        return _refused(request, refused)
    if format == "csv":
        filename = f"order-{order.order_id}.csv"
        return Response(
            report_csv(order),
            media_type="text/csv",
            headers={"Content-Disposition": f'attachment; filename="{filename}"'},
        )
    return report_of(order)
