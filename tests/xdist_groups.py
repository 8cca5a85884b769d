"""A pytest plugin: under `pytest-xdist --dist loadgroup`, a module whose tests share a
fixture set up once (scope module, class or package) runs whole on one worker.

`make test` runs the suite on several workers. Ungrouped tests go to whichever worker
is free; a module with a shared fixture (a served cell, a commissioned data directory,
rendered frames) would otherwise set that fixture up again on every worker that ran
one of its tests, and a test that reads what an earlier one left would find nothing.
Such a module's tests get an `xdist_group` mark named after the module, as do modules
that mark themselves.

pytest-xdist records a group by appending `@group` to each test's node id in the
worker, where its scheduler (in the controller) reads it. It writes the id to
`item._nodeid`; the pytest this suite pins reads a node's id from `item._id`, so the
suffix never reached the controller and every test was scheduled alone. After every
other plugin has run (`wrapper=True`), this hands the suffixed id to `_id` too.
"""

from __future__ import annotations

from collections.abc import Generator
from pathlib import Path

import pytest
from _pytest.nodeid import NodeId

SHARED_SCOPES = frozenset({"module", "class", "package"})


@pytest.hookimpl(wrapper=True)
def pytest_collection_modifyitems(
    config: pytest.Config, items: list[pytest.Item]
) -> Generator[None, None, None]:
    """Mark each test that uses a shared fixture with its module's group, before every
    other plugin (pytest-xdist reads the marks); after them, let pytest see the group
    pytest-xdist appended to the node id."""
    root = Path(str(config.rootpath))
    for item in items:
        if _uses_a_shared_fixture(item) and item.get_closest_marker("xdist_group") is None:
            try:
                name = item.path.relative_to(root).as_posix()
            except ValueError:  # collected from outside the root
                name = item.path.as_posix()
            item.add_marker(pytest.mark.xdist_group(name))
    yield
    for item in items:
        written = getattr(item, "_nodeid", None)
        if isinstance(written, str) and written != item.nodeid and hasattr(item, "_id"):
            item._id = NodeId.parse(written)


def _uses_a_shared_fixture(item: pytest.Item) -> bool:
    info = getattr(item, "_fixtureinfo", None)
    if info is None:
        return False
    return any(
        definition.scope in SHARED_SCOPES
        for definitions in info.name2fixturedefs.values()
        for definition in definitions
    )
