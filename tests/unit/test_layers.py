"""Every package of the server imports only what the table below allows it.

One table, `ALLOWED`, names for each package under server/ the other packages it may
import; a module's imports of its own package are always allowed. A package missing
from the table fails the test, so a new package states where it sits before it lands.
Checked on the sources' own imports (`ast`), lazy imports inside functions and
`TYPE_CHECKING` blocks included, so a shortcut shows up here and not as an import
cycle later.

A package is a directory with an `__init__.py` (`core/machine`, `drivers/sim`,
`storage/journal`); `server` is the entry point and the top package's own files. An
entry naming a module rather than a package (`bootstrap.cell`) allows that module
alone.

Read from the bottom up: `common` and `vision` import nothing of the server (vision is
pure geometry and image processing on arrays); drivers are device clients and
simulators and never reach the core, the transports or the composition root; the
core's machine, worker and operations sit above the drivers, storage and quality;
the read models (`views`) and the plant's services (`notify`, `orders`) above the
core; the transports (`api`, `mqtt`, `opcua`) above those; `bootstrap` composes them
all, and the command-line tools and the entry point start it.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SERVER = Path(__file__).resolve().parents[2] / "server"

# The running cell the transports, the order book and the embedded API drive.
CELL = "bootstrap.cell"

ALLOWED: dict[str, tuple[str, ...]] = {
    # the shared vocabulary and pure functions: nothing of the server
    "common": (),
    "vision": (),
    "core.infra": (),
    "core": (),
    # data at rest, policies, the settings
    # the policy reads the commands' roles from the catalogue
    "security": ("commands.catalogue", "common", "storage"),
    "settings": ("common", "security"),
    "storage": ("common", "storage.journal", "vision"),
    "storage.journal": ("common", "storage"),
    # devices
    "drivers": ("common", "drivers.sim", "vision"),
    "drivers.sim": ("drivers", "settings", "vision"),
    # the diagnostic bundle, read from the data directory
    # (and the care meter's pure rules, to judge the maintenance state as the cell does)
    "diagnostics": ("common", "core.worker.care_rules", "settings", "storage.journal"),
    # the command catalogue: each command declared once, above the machine's vocabulary
    "commands": ("common", "core.machine", "security", "storage"),
    # measuring a run
    "quality": ("drivers", "settings", "vision"),
    # the core
    "core.operations": (
        "common", "core.infra", "drivers", "quality", "settings", "storage", "vision",
    ),
    "core.machine": ("common", "core.operations", "drivers", "settings", "storage"),
    "core.worker": (
        "common", "core.infra", "core.machine", "core.operations", "drivers", "settings",
        "storage", "storage.journal",
    ),
    # the cell watching itself: its processes, links, error rate and parts' trends
    "watch": (
        "common", "core.worker", "quality", "settings", "storage.journal", "vision",
    ),
    # read models and the plant's services, above the core
    "views": (
        "common", "core.infra", "core.machine", "core.operations", "core.worker", "drivers",
        "quality", "security", "settings", "storage", "storage.journal", "vision",
    ),
    "notify": (
        "core.infra", "core.worker", "quality", "security", "settings", "storage.journal",
    ),
    "orders": (
        CELL, "core.infra", "core.machine", "core.worker", "drivers", "quality",
        "storage.journal",
    ),
    # transports
    "api": (
        CELL, "commands", "common", "core.infra", "core.machine", "core.operations", "core.worker",
        "diagnostics", "orders", "quality", "security", "settings", "storage", "storage.journal",
        "views", "watch",
    ),
    "mqtt": (
        CELL, "commands", "common", "core.infra", "core.machine", "core.worker", "quality",
        "security", "settings", "storage.journal",
    ),
    "mqtt.sparkplug": (
        CELL, "commands", "common", "core.infra", "core.machine", "core.worker", "mqtt",
        "security", "settings",
    ),
    "opcua": (
        CELL, "commands", "common", "core.infra", "core.machine", "security", "settings",
        "storage", "storage.journal", "views",
    ),
    # the façade starts the cell with its webhooks as the server does (bootstrap.plant)
    "embedded": (
        CELL, "bootstrap.plant", "core.machine", "core.operations", "core.worker", "settings",
    ),
    # the composition root, and what starts it
    "bootstrap": (
        "api", "commands", "common", "core.infra", "core.machine", "core.operations", "core.worker",
        "drivers", "drivers.sim", "mqtt", "mqtt.sparkplug", "notify", "opcua", "orders", "security",
        "settings", "storage", "storage.journal", "views", "vision", "watch",
    ),
    "cli": ("bootstrap", "diagnostics", "settings", "storage"),
    "line": ("api",),
    "server": (
        "api", "bootstrap", "cli", "common", "opcua", "settings", "storage", "vision",
    ),
}  # fmt: skip


def packages() -> set[str]:
    """Every package under server/, dotted from server/ (`server` for the top one)."""
    return {
        ".".join(init.parent.relative_to(SERVER).parts) or "server"
        for init in SERVER.rglob("__init__.py")
    }


PACKAGES = packages()
PACKAGES_DOTTED = {"server"} | {f"server.{p}" for p in PACKAGES if p != "server"}


def package_of(module: str) -> str:
    """The package a dotted `server...` module belongs to: the deepest one holding it."""
    parts = module.split(".")[1:]
    for end in range(len(parts), 0, -1):
        name = ".".join(parts[:end])
        if name in PACKAGES:
            return name
    return "server"


def imported_modules(path: Path) -> list[tuple[int, str]]:
    """Every absolute module of the server a source file imports, with its line."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            found.extend((node.lineno, alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, f"{path}:{node.lineno}: relative import"
            base = node.module or ""
            if base in PACKAGES_DOTTED:  # `from server.core import kpis` names a module
                found.extend((node.lineno, f"{base}.{alias.name}") for alias in node.names)
            else:
                found.append((node.lineno, base))
    return [(line, module) for line, module in found if module.split(".")[0] == "server"]


def allowed(own: str, module: str) -> bool:
    target = package_of(module)
    if target == own:
        return True
    for entry in ALLOWED[own]:
        if entry in PACKAGES:
            if target == entry:
                return True
        elif module == f"server.{entry}" or module.startswith(f"server.{entry}."):
            return True
    return False


def sources(package: str) -> list[Path]:
    folder = SERVER if package == "server" else SERVER.joinpath(*package.split("."))
    files = sorted(folder.glob("*.py"))
    assert files, package
    return files


def test_every_package_has_its_row() -> None:
    assert sorted(PACKAGES - ALLOWED.keys()) == [], "packages missing from ALLOWED"
    assert sorted(ALLOWED.keys() - PACKAGES) == [], "ALLOWED names packages that are gone"


def test_every_entry_names_a_package_or_a_module() -> None:
    for row in ALLOWED.values():
        for entry in row:
            path = SERVER.joinpath(*entry.split("."))
            assert entry in PACKAGES or path.with_suffix(".py").is_file(), entry


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_package_imports_only_what_its_row_allows(package: str) -> None:
    wrong = [
        f"{path.relative_to(SERVER.parent)}:{line}: {module}"
        for path in sources(package)
        for line, module in imported_modules(path)
        if not allowed(package, module)
    ]
    assert not wrong, f"{package} may import only {ALLOWED[package]}:\n" + "\n".join(wrong)


def test_the_lowest_layers_import_nothing_of_the_server() -> None:
    """vision stays pure and common stays shared: neither may ever gain a row."""
    assert ALLOWED["vision"] == ALLOWED["common"] == ()


def test_drivers_never_reach_the_core_or_above() -> None:
    """Drivers are device clients and simulators: the composition root joins them to the core."""
    above = ("core", "api", "mqtt", "opcua", "bootstrap", "views", "orders", "notify")
    for package in ("drivers", "drivers.sim"):
        reached = [e for e in ALLOWED[package] if e.split(".")[0] in above]
        assert not reached, (package, reached)
