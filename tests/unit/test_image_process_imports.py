"""What the operations hand to the image process lives in modules that import vision
and the quality's pure functions only.

The image process imports the module of each function it is handed
(`server/vision/process.py`). A function defined beside its operation brought the
whole operations package, the settings and pydantic into that process with it
(docs/benchmarks.md, Memory: the cell with every device real). Found here from the sources:
each `IMAGE_PROCESS.call(f, ...)` in `server/core/operations/`, `f`'s module
imported in a fresh interpreter, and what that loaded.
"""

from __future__ import annotations

import ast
from pathlib import Path

from tests.processes import ROOT, run_python

OPERATIONS = ROOT / "server" / "core" / "operations"
# Never in the image process of a cell with a real camera.
HEAVY = ("pydantic", "server.core", "server.settings", "server.storage", "fastapi")


def handed_to_the_image_process(path: Path) -> dict[str, str]:
    """Each function `path` hands to IMAGE_PROCESS.call, with the module it comes from
    ("" when it is defined in `path` itself)."""
    tree = ast.parse(path.read_text())
    origin = {
        alias.asname or alias.name: node.module or ""
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom)
        for alias in node.names
    }
    handed = {}
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr == "call"
            and isinstance(node.func.value, ast.Name)
            and node.func.value.id == "IMAGE_PROCESS"
            and node.args
            and isinstance(node.args[0], ast.Name)
        ):
            name = node.args[0].id
            handed[name] = origin.get(name, "")
    return handed


def test_every_function_handed_over_comes_from_a_light_module() -> None:
    handed = {
        f"{path.name}: {name}": module
        for path in sorted(OPERATIONS.glob("*.py"))
        for name, module in handed_to_the_image_process(path).items()
    }
    assert len(handed) >= 5, handed  # the inspection, matching, teaching, both calibrations
    defined_beside = sorted(where for where, module in handed.items() if not module)
    assert not defined_beside, f"defined in an operations module: {defined_beside}"
    modules = sorted(set(handed.values()))
    probe = (
        "import importlib, sys\n"
        f"for name in {modules!r}: importlib.import_module(name)\n"
        "print(' '.join(sorted(sys.modules)))\n"
    )
    done = run_python("-c", probe)
    assert done.returncode == 0, done.stderr
    loaded = done.stdout.split()
    heavy = sorted(m for m in loaded if m.split(".")[0] in HEAVY or m.startswith(HEAVY))
    assert not heavy, f"{modules} load {heavy}"
