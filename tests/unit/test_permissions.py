"""Tightening a data directory takes permissions away, never adds them, never follows links."""

from __future__ import annotations

import stat

from server.storage.permissions import private_file, tighten_data_directory


def mode(path) -> int:
    return stat.S_IMODE(path.lstat().st_mode)


def test_only_looser_bits_are_taken_away_and_the_log_keeps_group_read(tmp_path) -> None:
    data = tmp_path / "data"
    (data / "logs").mkdir(parents=True)
    log_file = data / "logs" / "glue_cell.log"
    for path, loose in [
        (data / "journal.db", 0o644),
        (data / "owner-read-only.json", 0o400),
        (log_file, 0o664),
        (data / "logs" / "glue_cell.log.1", 0o644),
    ]:
        path.write_text("x")
        path.chmod(loose)
    outside = tmp_path / "elsewhere.txt"
    outside.write_text("x")
    outside.chmod(0o644)
    (data / "link").symlink_to(outside)
    data.chmod(0o755)
    changes = tighten_data_directory(data, [log_file])
    assert mode(data) == 0o700 and mode(data / "logs") == 0o700
    assert mode(data / "journal.db") == 0o600
    assert mode(data / "owner-read-only.json") == 0o400  # never loosened
    assert mode(log_file) == 0o640 and mode(data / "logs" / "glue_cell.log.1") == 0o640
    assert mode(outside) == 0o644  # a link's target is not the cell's to change
    assert ". 755 -> 700" in changes and "journal.db 644 -> 600" in changes
    assert tighten_data_directory(data, [log_file]) == []  # nothing more to say


def test_a_missing_data_directory_is_made_private(tmp_path) -> None:
    data = tmp_path / "new" / "data"
    assert tighten_data_directory(data) == []
    assert mode(data) == 0o700


def test_a_private_file_is_0600_new_or_not(tmp_path) -> None:
    new, old = tmp_path / "new.db", tmp_path / "old.db"
    old.write_bytes(b"kept")
    old.chmod(0o666)
    private_file(new)
    private_file(old)
    assert mode(new) == 0o600 and mode(old) == 0o600 and old.read_bytes() == b"kept"
