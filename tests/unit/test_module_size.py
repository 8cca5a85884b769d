"""No Python module of the server or the clients grows past 600 lines.

A module that long holds more than one concern and no longer reads in one sitting;
split it by concern instead (a package, or sibling modules). The device simulators
under server/drivers/sim/ are exempt: each models one whole device and its protocol.
"""

from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
LIMIT = 600
CHECKED = (ROOT / "server", ROOT / "clients")
EXEMPT = (ROOT / "server" / "drivers" / "sim",)


def checked_modules() -> list[Path]:
    """Every .py file under server/ and clients/, the simulators left out."""
    return sorted(
        path
        for top in CHECKED
        for path in top.rglob("*.py")
        if not any(path.is_relative_to(exempt) for exempt in EXEMPT)
    )


def line_count(path: Path) -> int:
    return len(path.read_text(encoding="utf-8").splitlines())


def test_the_check_sees_both_trees() -> None:
    modules = checked_modules()
    assert any(p.is_relative_to(ROOT / "server") for p in modules)
    assert any(p.is_relative_to(ROOT / "clients") for p in modules)


@pytest.mark.parametrize("top", CHECKED, ids=lambda p: p.name)
def test_no_module_is_over_600_lines(top: Path) -> None:
    too_long = {
        str(path.relative_to(ROOT)): count
        for path in checked_modules()
        if path.is_relative_to(top) and (count := line_count(path)) > LIMIT
    }
    assert too_long == {}, f"modules over {LIMIT} lines (split them by concern): {too_long}"
