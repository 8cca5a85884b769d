"""The layers import downwards only: a driver or a vision module never reaches up.

Drivers are device clients and simulators; the composition root
(server/bootstrap/) is what joins them to the core. Vision is pure geometry and
image processing on arrays. Checked on the source's own imports (`ast`), lazy
imports inside functions included, so a shortcut shows up here and not as an
import cycle later.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SERVER = Path(__file__).resolve().parents[2] / "server"

# What a package must not import (a module or anything under it).
FORBIDDEN = {
    "drivers": (
        "server.core",
        "server.api",
        "server.bootstrap",
        "server.bootstrap.cell",
        "server.bootstrap.app",
    ),
}
# What a package may import of the server besides itself; everything else is refused.
ONLY = {
    "vision": ("server.vision",),
}


def imported_modules(path: Path) -> list[tuple[int, str]]:
    """Every absolute module a source file imports, with its line."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            found.extend((node.lineno, alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, f"{path}:{node.lineno}: relative import"
            if node.module == "server":  # `from server import core` names the module
                found.extend((node.lineno, f"server.{alias.name}") for alias in node.names)
            else:
                found.append((node.lineno, node.module or ""))
    return found


def under(module: str, prefixes: tuple[str, ...]) -> bool:
    return any(module == p or module.startswith(p + ".") for p in prefixes)


def sources(package: str) -> list[Path]:
    files = sorted((SERVER / package).rglob("*.py"))
    assert files, package
    return files


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_package_does_not_import_the_layers_above(package: str) -> None:
    wrong = [
        f"{path.relative_to(SERVER.parent)}:{line}: {module}"
        for path in sources(package)
        for line, module in imported_modules(path)
        if under(module, FORBIDDEN[package])
    ]
    assert not wrong, "\n".join(wrong)


@pytest.mark.parametrize("package", sorted(ONLY))
def test_package_imports_only_itself_of_the_server(package: str) -> None:
    wrong = [
        f"{path.relative_to(SERVER.parent)}:{line}: {module}"
        for path in sources(package)
        for line, module in imported_modules(path)
        if under(module, ("server",)) and not under(module, ONLY[package])
    ]
    assert not wrong, "\n".join(wrong)
