"""The glue dispenser's flow model, replayed: the flow leaving the nozzle at given times.

Shared by the glue simulator (its reading) and the simulated camera (the bead it renders), so
the bead follows the very flow the dispenser reports.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

FLOW_TIME_CONSTANT_S = 0.05


def flow_at(
    history: Sequence[tuple[float, bool, float]], times: Sequence[float], speed: float
) -> list[float]:
    """The dispenser model's flow (ml/min) at each ascending time.time() in `times`.

    `history` is `GlueSimulator.history`: (time, valve open, target flow) per change. The flow
    approaches the target first-order while open (FLOW_TIME_CONSTANT_S of simulated time,
    `speed` being the simulator's speed factor) and is zero while closed.
    """
    out: list[float] = []
    k = 0
    flow, since, is_open, target = 0.0, -math.inf, False, 0.0
    for t in times:
        while k < len(history) and history[k][0] <= t:
            at, now_open, new_target = history[k]
            if is_open and now_open and math.isfinite(since):
                gain = 1 - math.exp(-(at - since) * speed / FLOW_TIME_CONSTANT_S)
                flow += (target - flow) * gain
            elif not now_open:
                flow = 0.0
            since, is_open, target = at, now_open, new_target
            k += 1
        if not is_open:
            out.append(0.0)
            continue
        gain = 1 - math.exp(-max(t - since, 0.0) * speed / FLOW_TIME_CONSTANT_S)
        out.append(flow + (target - flow) * gain)
    return out
