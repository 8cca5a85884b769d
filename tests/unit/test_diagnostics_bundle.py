"""The bundle's pure parts: the log's end from a line's start, the archive's layout."""

from __future__ import annotations

import io
import tarfile

from server.diagnostics.bundle import _tail, archive


def test_the_log_tail_starts_at_a_line(tmp_path) -> None:
    log = tmp_path / "glue_cell.log"
    log.write_bytes(b"".join(b"line %04d\n" % n for n in range(1000)))
    tail = _tail(log, 95)
    assert tail.startswith(b"line ") and tail.endswith(b"line 0999\n")
    assert len(tail.splitlines()) == 9  # the partly cut first line left out
    assert _tail(log, 1_000_000) == log.read_bytes()


def test_the_archive_holds_each_file_under_one_directory() -> None:
    data = archive({"a.json": b"{}\n", "logs/x.log.tail": b"x\n"}, "bundle-1")
    with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as tar:
        names = {m.name: m.mode for m in tar.getmembers()}
        assert tar.extractfile("bundle-1/logs/x.log.tail").read() == b"x\n"  # type: ignore[union-attr]
    assert names == {"bundle-1/a.json": 0o644, "bundle-1/logs/x.log.tail": 0o644}
