"""Which answers are retried, and how long to wait before the next attempt.

Why these: a timeout, a refused or reset connection, 408 (the receiver gave up
waiting), 429 (too many) and 5xx (the receiver is unwell) may succeed later; any
other answer is the receiver's verdict on this notice, and sending it again
would get the same one (a 400 stays a 400). A redirect is not followed: the
signed notice goes where it was configured to, or nowhere.

The wait doubles from `webhook_retry_delay` up to `webhook_retry_max_delay`,
with up to a fifth more at random, so the cells of a line whose receiver came
back do not all retry in the same instant. A Retry-After the receiver sent is
honoured within the same ceiling.
"""

from __future__ import annotations

import random
from enum import StrEnum

RETRIED_STATUSES = frozenset({408, 429})
JITTER = 0.2


class Verdict(StrEnum):
    """What an answer means for the notice."""

    DELIVERED = "delivered"
    RETRY = "retry"
    REFUSED = "refused"  # final: a 4xx other than 408/429, or a 3xx


def verdict(status: int) -> Verdict:
    if 200 <= status < 300:
        return Verdict.DELIVERED
    if status in RETRIED_STATUSES or status >= 500:
        return Verdict.RETRY
    return Verdict.REFUSED


def delay(attempt: int, first: float, ceiling: float, retry_after: float | None = None) -> float:
    """Seconds to wait after failed attempt number `attempt` (1, 2, ...)."""
    base = min(first * 2 ** (attempt - 1), ceiling)
    wait = min(base * (1 + JITTER * random.random()), ceiling)
    if retry_after is not None:
        wait = max(wait, min(retry_after, ceiling))
    return wait


def retry_after_seconds(value: str | None) -> float | None:
    """A Retry-After given in seconds (an HTTP date is ignored: the backoff applies)."""
    if value is None:
        return None
    try:
        seconds = float(value.strip())
    except ValueError:
        return None
    return seconds if 0 <= seconds < float("inf") else None
