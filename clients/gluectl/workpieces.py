"""gluectl's commands of the workpiece library and the calibrations: `workpieces`,
`create-workpiece`, `calibrate-robot`, `calibrate-camera`, and the `marker` group that
teaches the marker layout robot calibration uses.
"""

from __future__ import annotations

from typing import Annotated, Any

import typer
from rich.table import Table
from rich.text import Text

from clients.gluectl.calls import call, command, options_for, show
from clients.gluectl.format import value as _value
from clients.gluectl.format import when as _when
from clients.gluectl.options import JsonFlag


def workpieces_table(rows: list[dict[str, Any]]) -> Table:
    table = Table(title="workpiece library", title_justify="left")
    for column in ("id", "name", "source", "outline points", "fill", "created"):
        table.add_column(column, overflow="fold")
    for row in rows:
        spray = row.get("spray") or {}
        table.add_row(
            *(
                Text(v)
                for v in (
                    _value(row.get("id")),
                    _value(row.get("name")),
                    _value(row.get("source")),
                    str(len(row.get("outline_mm") or [])),
                    _value(spray.get("fill")),
                    _when(row.get("created_at"), short=True),
                )
            )
        )
    return table


def marker_table(layout: dict[str, Any]) -> Table:
    """GET /calibration/markers: in force and draft, marker by marker."""
    position = (layout.get("robot") or {}).get("position")
    where = _value(position[:3] if isinstance(position, list) else None)
    table = Table(title=f"markers ({layout.get('source')}); robot at {where}", title_justify="left")
    for column in ("marker", "in force (mm)", "draft (mm)", "how"):
        table.add_column(column, overflow="fold")
    drafts = layout.get("draft") or []
    for i, (x, y) in enumerate(layout.get("in_force") or []):
        draft = drafts[i] if i < len(drafts) else None
        typed = f"{_value(draft['x_mm'])}, {_value(draft['y_mm'])}" if draft else "—"
        how = draft["how"] if draft else "missing"
        table.add_row(*(Text(v) for v in (str(i), f"{_value(x)}, {_value(y)}", typed, how)))
    return table


marker_app = typer.Typer(help="The marker layout robot calibration uses, taught with the robot.")


@marker_app.command("list")
def marker_list(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """The layout in force and the draft being taught."""
    options = options_for(ctx, json_flag)
    show(options, call(options, lambda c: c.markers()), marker_table)


@marker_app.command("teach")
def marker_teach(
    ctx: typer.Context,
    marker: Annotated[int, typer.Argument(min=0, max=8, help="ArUco marker id, 0-8.")],
    json_flag: JsonFlag = False,
) -> None:
    """Record the tool's current x, y as marker N in the draft (maintenance role)."""
    options = options_for(ctx, json_flag)
    show(options, call(options, lambda c: c.teach_marker(marker)), marker_table)


@marker_app.command("apply")
def marker_apply(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """Put the draft in force once all nine pass the layout check (maintenance role)."""
    options = options_for(ctx, json_flag)
    show(options, call(options, lambda c: c.apply_markers()), marker_table)


def calibrate_robot(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """Fit the image → robot map from ArUco markers 0-8 (maintenance role)."""
    command(ctx, json_flag, lambda c: c.calibrate_robot())


def calibrate_camera(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """Calibrate the camera's intrinsics from chessboard views (maintenance role)."""
    command(ctx, json_flag, lambda c: c.calibrate_camera())


def create_workpiece(
    ctx: typer.Context,
    name: Annotated[str | None, typer.Option("--name", help="The workpiece's name.")] = None,
    workpiece_id: Annotated[
        str | None, typer.Option("--id", help="Store under this id (default: the next wp-NNNN).")
    ] = None,
    if_new: Annotated[
        bool,
        typer.Option(
            "--if-new",
            help="Store it only if it matches no stored part; `gluectl state` then shows "
            "which part it matches and how well (operation_result.similar).",
        ),
    ] = False,
    json_flag: JsonFlag = False,
) -> None:
    """Capture the largest part on the table into the library."""
    command(ctx, json_flag, lambda c: c.create_workpiece(name, workpiece_id, if_new))


def workpieces(ctx: typer.Context, json_flag: JsonFlag = False) -> None:
    """List the workpiece library."""
    options = options_for(ctx, json_flag)
    show(options, call(options, lambda c: c.workpieces()), workpieces_table)
