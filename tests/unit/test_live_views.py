"""Who may open one more /ws view: the overall, per-token and reserved limits, and revocation."""

from __future__ import annotations

from server.api.live_views import CLOSE_UNAUTHORIZED, LiveViews
from server.security.tokens import Principal, Role

VIEWER = Principal("v1", "viewer", Role.VIEWER)
OPERATOR = Principal("o1", "operator", Role.OPERATOR)
MAINTENANCE = Principal("m1", "maintenance", Role.MAINTENANCE)


async def test_reserved_slots_never_leave_viewers_and_operators_none() -> None:
    views = LiveViews(max_clients=2, per_token=10, reserved=5)  # capped at all but one
    assert views.refusal(VIEWER) is None
    views.open(VIEWER)
    assert "kept for maintenance and admin" in (views.refusal(OPERATOR) or "")
    assert views.refusal(MAINTENANCE) is None
    views.open(MAINTENANCE)
    assert "too many clients" in (views.refusal(MAINTENANCE) or "")


async def test_closing_a_view_frees_its_slot_once() -> None:
    views = LiveViews(max_clients=3, per_token=1)
    view = views.open(VIEWER)
    assert "per_token" in (views.refusal(VIEWER) or "")
    views.close(view)
    views.close(view)  # the connection's cleanup may run after an early close
    assert views.count == 0 and views.refusal(VIEWER) is None


async def test_revoking_ends_open_views_and_any_the_token_opens_later() -> None:
    views = LiveViews(max_clients=10)
    first, other = views.open(VIEWER), views.open(OPERATOR)
    assert views.revoke(VIEWER.token_id) == 1
    assert first.ended.done() and first.ended.result()[0] == CLOSE_UNAUTHORIZED
    assert not other.ended.done()
    late = views.open(VIEWER)  # authenticated just before the revocation
    assert late.ended.done() and late.ended.result()[0] == CLOSE_UNAUTHORIZED
