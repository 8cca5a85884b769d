"""The draft marker layout on disk: survives a restart, 0600, and an applied layout is put
back in force at start only when the settings still accept it."""

from __future__ import annotations

import stat

from server.bootstrap.cell import restore_taught_layout
from server.settings.model import DEFAULT_MARKER_POSITIONS_MM, Settings
from server.storage.marker_layout import MarkerLayoutStore

SHIFTED = [(x + 5.0, y) for x, y in DEFAULT_MARKER_POSITIONS_MM]


def test_the_draft_and_the_applied_layout_survive_a_restart(tmp_path) -> None:
    store = MarkerLayoutStore(tmp_path)
    store.set_marker(3, 401.25, -2.5, "taught")
    assert store.missing() == [0, 1, 2, 4, 5, 6, 7, 8]
    for i, (x, y) in enumerate(SHIFTED):
        store.set_marker(i, x, y, "typed")
    store.record_applied(SHIFTED)
    again = MarkerLayoutStore(tmp_path)
    assert again.draft_layout() == SHIFTED and again.applied == SHIFTED
    assert again.draft[3] is not None and again.draft[3].how == "typed"
    assert stat.S_IMODE(store.path.stat().st_mode) == 0o600


def test_a_corrupt_file_is_set_aside_not_fatal(tmp_path) -> None:
    store = MarkerLayoutStore(tmp_path)
    store.set_marker(0, 1.0, 2.0, "typed")
    store.path.write_text("{not json", encoding="utf-8")
    again = MarkerLayoutStore(tmp_path)
    assert again.missing() == list(range(9)) and again.applied is None
    assert list(store.path.parent.glob("markers.corrupt-*"))


def test_an_applied_layout_is_put_back_in_force_if_the_settings_accept_it(tmp_path) -> None:
    settings = Settings(data_path=tmp_path)
    restore_taught_layout(settings, SHIFTED)
    assert [tuple(p) for p in settings.marker_positions_mm] == SHIFTED
    narrow = Settings(data_path=tmp_path, workspace_max_mm=(552.0, 400.0, 500.0))
    restore_taught_layout(narrow, SHIFTED)  # marker 2 at x=555 is now outside: left out
    assert [tuple(p) for p in narrow.marker_positions_mm] == DEFAULT_MARKER_POSITIONS_MM
