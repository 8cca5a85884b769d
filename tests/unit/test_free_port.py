"""The suite's servers get ports a browser will open.

Chromium refuses a list of ports outright (net::ERR_UNSAFE_PORT): a dashboard served on
10080, a port `free_port` may pick at random, failed a browser test in a full run.
"""

from __future__ import annotations

import random

from tests.serving import BROWSER_REFUSED_PORTS, free_port


def test_a_port_a_browser_refuses_is_never_chosen(monkeypatch) -> None:
    picks = iter([10080, 6000, 10081])
    monkeypatch.setattr(random, "randrange", lambda *_: next(picks))
    assert free_port() == 10081


def test_the_refused_ports_include_those_above_the_privileged_range() -> None:
    assert {10080, 6000, 6665, 6697, 5060, 2049} <= BROWSER_REFUSED_PORTS
