"""The pure parts of slowing guessing: the bad-token throttle and the folding of repeated
refusals (server/security/throttle.py, server/api/audit_repeats.py), on a given clock."""

from __future__ import annotations

from server.api.audit_repeats import RepeatFolder
from server.security.throttle import AuthThrottle, client_key

KIND = ("anonymous", "10.0.0.5", "GET /state", "refused (401)", "the token is unknown or revoked")


def test_an_address_is_locked_out_after_the_limit_within_the_window_and_only_it() -> None:
    throttle = AuthThrottle(limit=3, window=10, lockout=30)
    assert [throttle.failed("10.0.0.5", t) for t in (0, 1, 2)] == [False, False, True]
    assert throttle.retry_after("10.0.0.5", 2) == 30
    assert throttle.retry_after("10.0.0.5", 31.5) == 1  # whole seconds, never 0 while locked
    assert throttle.retry_after("10.0.0.5", 32) is None
    assert throttle.retry_after("10.0.0.6", 2) is None


def test_failures_spread_wider_than_the_window_never_lock() -> None:
    throttle = AuthThrottle(limit=3, window=10, lockout=30)
    assert not any(throttle.failed("10.0.0.5", t) for t in range(0, 100, 6))
    assert throttle.retry_after("10.0.0.5", 100) is None


def test_ipv6_is_counted_per_64_and_ipv4_mapped_as_ipv4() -> None:
    assert client_key("2001:db8::1") == client_key("2001:db8::ffff:1") == "2001:db8::/64"
    assert client_key("2001:db8:0:1::1") != client_key("2001:db8::1")
    assert client_key("::ffff:10.0.0.5") == "10.0.0.5"
    assert client_key("unknown") == "unknown"
    throttle = AuthThrottle(limit=2, window=10, lockout=30)
    throttle.failed("2001:db8::1", 0)
    assert throttle.failed("2001:db8::2", 1)
    assert throttle.retry_after("2001:db8::3", 2) == 29


def test_the_table_of_addresses_is_bounded() -> None:
    throttle = AuthThrottle(limit=5, window=60, lockout=60, max_addresses=100)
    for n in range(10_000):
        throttle.failed(f"10.{n // 65536}.{n // 256 % 256}.{n % 256}", n / 1000)
    assert len(throttle) == 100


def test_the_first_refusal_is_written_at_once_and_the_rest_as_one_row_with_a_count() -> None:
    folder = RepeatFolder(window=60)
    assert folder.offer(KIND, 0.0) == [(KIND, 1, 0.0)]
    assert all(folder.offer(KIND, t / 10) == [] for t in range(1, 100))
    assert folder.due(59.0) == []
    assert folder.due(60.0) == [(KIND, 99, 9.9)]
    assert folder.due(120.0) == []  # a quiet window: the kind is forgotten
    assert len(folder) == 0
    assert folder.offer(KIND, 200.0) == [(KIND, 1, 200.0)]  # written at once again


def test_a_repetition_that_goes_on_is_one_row_per_window() -> None:
    folder = RepeatFolder(window=10)
    written = folder.offer(KIND, 0)
    for t in range(1, 100):
        written += folder.offer(KIND, t)
        written += folder.due(t)
    written += folder.drain()
    assert sum(count for _, count, _ in written) == 100
    assert len(written) <= 11


def test_a_window_not_yet_swept_still_counts_every_refusal() -> None:
    folder = RepeatFolder(window=10)
    folder.offer(KIND, 0)
    folder.offer(KIND, 5)
    assert folder.offer(KIND, 15) == [(KIND, 1, 5)]  # the fold; 15 is folded on
    assert folder.drain() == [(KIND, 1, 15)]
    assert folder.drain() == []


def test_other_kinds_are_not_folded_together_and_the_table_is_bounded() -> None:
    folder = RepeatFolder(window=60, max_kinds=2)
    other = (*KIND[:3], "refused (429)", KIND[4])
    third = (*KIND[:2], "POST /start", *KIND[3:])
    assert folder.offer(KIND, 0) and folder.offer(other, 0) and folder.offer(third, 0)
    assert folder.offer(third, 1) == [(third, 1, 1)]  # past the bound: written, not folded
    assert len(folder) == 2
