"""A journal filter of a closed set takes the values its column really holds.

The filters refuse any other value (422): a set left behind when a notice kind, a fault
class or an order state is added would refuse real rows. The journal's schema cannot
import those definitions (it sits below them), so this holds them together.
"""

from __future__ import annotations

from typing import get_args

from server.core.machine.faults import Classification
from server.core.machine.transitions import OPERATION_OF_STATE
from server.orders.model import DEFECTIVE, GOOD, OrderState
from server.settings.webhooks import NOTICE_KINDS
from server.storage.journal.schema import FILTERS


def values(table: str, column: str) -> set[str]:
    [spec] = [f for f in FILTERS[table] if f.column == column]
    return set(spec.values)


def test_each_closed_filter_takes_its_columns_values() -> None:
    assert values("operations", "kind") == set(OPERATION_OF_STATE.values())
    assert values("errors", "classification") == set(get_args(Classification))
    assert values("webhook_deliveries", "kind") == set(NOTICE_KINDS)
    assert values("orders", "state") == {state.value for state in OrderState}
    assert values("inspections", "verdict") == {GOOD, DEFECTIVE}
