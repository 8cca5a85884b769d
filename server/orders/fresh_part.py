"""The simulated cell's next part outside an order: a part whose spray run completed leaves
the table before the next run starts, and a fresh one lies where it lay.

A real cell has a person or a conveyor do this; an order does it between its own parts
(`OrderBook`). Without it, every start sprays the same simulated part again, and its camera
draws every bead ever laid on it: each run's render, and the memory it leaves behind, would
grow with the runs before it. A run that did not complete (stopped, failed, cancelled)
leaves its part where it is, with its glue, as a real one would stay for a person to see.
"""

from __future__ import annotations

from collections.abc import Callable

from server.core.worker.runs import RunEnded
from server.core.worker.view import CellView

SPRAY_RUN = "trajectory"


def fresh_part_per_run(view: CellView, present_next_part: Callable[[], None]) -> None:
    """Call `present_next_part` as a spray run starts after one that completed."""
    finished = False

    def ended(run: RunEnded) -> None:
        nonlocal finished
        if run.operation == SPRAY_RUN:
            finished = run.outcome == "completed"

    def started(operation: str) -> None:
        nonlocal finished
        if operation == SPRAY_RUN and finished:
            finished = False
            present_next_part()

    view.on_run_ended(ended)
    view.on_run_started(started)
