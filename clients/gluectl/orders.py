"""gluectl's `order` group: production orders (N good parts of a workpiece, run one by
one), their tables and their report.
"""

from __future__ import annotations

from typing import Annotated, Any

import typer
from rich.table import Table
from rich.text import Text

from clients.gluectl.calls import call, options_for, show
from clients.gluectl.format import key_values as _key_values
from clients.gluectl.format import value as _value
from clients.gluectl.format import when as _when
from clients.gluectl.options import JsonFlag


def order_table(order: dict[str, Any]) -> Table:
    rows = [
        ("order", order["order_id"]),
        ("workpiece", order["workpiece_id"]),
        ("state", order["state"]),
        ("good", f"{order['good']} of {order['quantity']}"),
        (
            "defective",
            f"{order['defective']} ({order['defects_in_row']} in a row, "
            f"limit {order['defect_limit']})",
        ),
        ("reason", _value(order.get("reason"))),
        ("created", f"{_when(order['created_at'])} by {order['created_by']}"),
    ]
    return _key_values("order", rows)


def orders_table(listing: dict[str, Any]) -> Table:
    table = Table(title="production orders", title_justify="left")
    for column in ("order", "workpiece", "state", "good", "defective", "reason"):
        table.add_column(column, overflow="fold")
    for o in listing["orders"]:
        marker = " *" if o["order_id"] == listing.get("active") else ""
        table.add_row(
            *(
                Text(v)
                for v in (
                    o["order_id"] + marker,
                    o["workpiece_id"],
                    o["state"],
                    f"{o['good']}/{o['quantity']}",
                    str(o["defective"]),
                    _value(o.get("reason")),
                )
            )
        )
    return table


def order_report_table(report: dict[str, Any]) -> Table:
    order = report["order"]
    table = Table(
        title=f"order {order['order_id']}: {order['good']}/{order['quantity']} good, "
        f"{order['defective']} defective ({order['state']})",
        title_justify="left",
    )
    for column in ("part", "run", "ended", "verdict", "precision mm", "glue ml", "reasons"):
        table.add_column(column, overflow="fold")
    for p in report["parts"]:
        table.add_row(
            *(
                Text(v)
                for v in (
                    str(p["part"]),
                    p["run_id"],
                    _when(p["ended_at"], short=True),
                    p["verdict"],
                    _value(p.get("precision_mean_mm")),
                    _value(p.get("glue_ml")),
                    "; ".join(p["reasons"]),
                )
            )
        )
    return table


order_app = typer.Typer(help="Production orders: N good parts of a workpiece, run one by one.")


OrderIdArg = Annotated[str, typer.Argument(help="The order's id (gluectl order list).")]


def _order_answer(answer: dict[str, Any]) -> dict[str, Any]:
    return answer.get("order", answer)


@order_app.command("start")
def order_start(
    ctx: typer.Context,
    workpiece: Annotated[str, typer.Argument(help="The library workpiece to make.")],
    quantity: Annotated[int, typer.Argument(min=1, help="How many good parts.")],
    json_flag: JsonFlag = False,
) -> None:
    """Make QUANTITY good parts of WORKPIECE: runs at once, or queues (operator role)."""
    options = options_for(ctx, json_flag)
    answer = call(options, lambda c: c.create_order(workpiece, quantity))
    show(options, answer, lambda a: order_table(_order_answer(a)))


@order_app.command("show")
def order_show(ctx: typer.Context, order_id: OrderIdArg, json_flag: JsonFlag = False) -> None:
    """One order: state, why, good and defective parts."""
    options = options_for(ctx, json_flag)
    show(options, call(options, lambda c: c.order(order_id)), order_table)


@order_app.command("list")
def order_list(
    ctx: typer.Context,
    state: Annotated[
        str | None, typer.Option("--state", help="queued, running, held, completed, closed")
    ] = None,
    json_flag: JsonFlag = False,
) -> None:
    """The orders, newest first (* marks the active one)."""
    options = options_for(ctx, json_flag)
    show(options, call(options, lambda c: c.orders(state)), orders_table)


@order_app.command("close")
def order_close(ctx: typer.Context, order_id: OrderIdArg, json_flag: JsonFlag = False) -> None:
    """End an order before its quantity; a run under way goes on (operator role)."""
    options = options_for(ctx, json_flag)
    show(options, call(options, lambda c: c.close_order(order_id)), order_table)


@order_app.command("resume")
def order_resume(ctx: typer.Context, order_id: OrderIdArg, json_flag: JsonFlag = False) -> None:
    """Continue a held order; the cell must be IDLE (reset it first) (operator role)."""
    options = options_for(ctx, json_flag)
    answer = call(options, lambda c: c.resume_order(order_id))
    show(options, answer, lambda a: order_table(_order_answer(a)))


@order_app.command("report")
def order_report(
    ctx: typer.Context,
    order_id: OrderIdArg,
    csv_flag: Annotated[bool, typer.Option("--csv", help="The report as CSV on stdout.")] = False,
    json_flag: JsonFlag = False,
) -> None:
    """Every part of an order: run, time, verdict, precision, glue used, reasons."""
    options = options_for(ctx, json_flag)
    if csv_flag:
        typer.echo(call(options, lambda c: c.order_report_csv(order_id)), nl=False)
        return
    show(options, call(options, lambda c: c.order_report(order_id)), order_report_table)
