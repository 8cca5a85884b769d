"""The robot simulator remembers its last `PATH_SIZE` segments, not every move it made.

It runs in the server's own process on the simulated cell, for as long as the server
runs: a path that grew by every move of every run was memory the cell never gave back.
"""

from __future__ import annotations

import itertools

import pytest

from server.drivers.sim import robot_sim
from server.drivers.sim.robot_sim import RobotSimulator


def move_and_stop(sim: RobotSimulator, x: float) -> None:
    """A move cut short at once: one interrupted segment on the path."""
    sim.handle(
        {"jsonrpc": "2.0", "id": 1, "method": "moveL", "params": [[x, 0, 200, 180, 0, 0], 50, 500]}
    )
    sim.handle({"jsonrpc": "2.0", "id": 2, "method": "stop", "params": []})


def test_the_executed_path_keeps_the_newest_segments_up_to_its_bound(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(robot_sim, "PATH_SIZE", 5)
    sim = RobotSimulator()
    for step in range(12):
        move_and_stop(sim, 300.0 + 10 * step)
    path = sim.executed_path
    assert len(path) == 5
    assert [s.interrupted for s in path] == [True] * 5
    # the newest five: each one starts where the one before it was stopped
    assert all(a.end == b.start for a, b in itertools.pairwise(path))
    assert len(sim.path_snapshot()) == 5


def test_the_bound_is_far_above_what_a_test_or_a_part_needs() -> None:
    assert robot_sim.PATH_SIZE >= 10_000
    sim = RobotSimulator()
    for step in range(50):
        move_and_stop(sim, 300.0 + step)
    assert len(sim.executed_path) == 50
