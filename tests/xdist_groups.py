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
other plugin has run (`wrapper=True`), this hands the suffixed id to `_id` too. (The
controller shows a parametrized one as `test[a-b]@group]`: it reads the parameters up to
the last `]`.)

pytest-xdist also needs every test's id to be its own: its scheduler keeps tests by id,
so tests sharing one would run once between them. Under the pinned pytest,
schemathesis's tests of one function (one per API operation) all get the function's
id; before anything reads the ids, each of them gets its name's instead
(`test_with_the_admin_token[GET /state]`), as a parametrized test's id has its
parameters.
"""

from __future__ import annotations

from collections import Counter
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
    _ids_of_their_own(items)
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


def _ids_of_their_own(items: list[pytest.Item]) -> None:
    """A test whose id another test has too gets one from its parent's id and its name."""
    counts = Counter(item.nodeid for item in items)
    for item in items:
        if counts[item.nodeid] > 1 and item.parent is not None and hasattr(item, "_id"):
            item._id = NodeId.parse(f"{item.parent.nodeid}::{item.name}")


def _uses_a_shared_fixture(item: pytest.Item) -> bool:
    info = getattr(item, "_fixtureinfo", None)
    if info is None:
        return False
    return any(
        definition.scope in SHARED_SCOPES
        for definitions in info.name2fixturedefs.values()
        for definition in definitions
    )
