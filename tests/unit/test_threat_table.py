"""The threat table in docs/security.md names tests that exist.

Each row of "Threats at each boundary" cites the test that shows its protection; a
renamed or removed test would leave the table pointing at nothing, so every path and
`file::test` it names is looked up here.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
CITED = re.compile(r"`((?:tests|bench)/[\w/]+\.py)(?:::(\w+))?`")


def threat_table() -> str:
    text = (ROOT / "docs" / "security.md").read_text(encoding="utf-8")
    start = text.index("## Threats at each boundary")
    return text[start : text.index("\n## ", start + 1)]


def test_every_boundary_has_a_row() -> None:
    rows = [line for line in threat_table().splitlines() if line.startswith("| ")][2:]
    boundaries = {row.split("|")[1].strip() for row in rows}
    for boundary in ("HTTP", "WebSocket", "OPC UA", "MQTT", "Webhooks", "Files", "Logs"):
        assert any(boundary in named for named in boundaries), boundary


def test_every_test_the_table_cites_exists() -> None:
    cited = CITED.findall(threat_table())
    assert len(cited) > 10
    for path, name in cited:
        source = ROOT / path
        assert source.is_file(), path
        if name:
            pattern = rf"^(async )?def {name}\("
            assert re.search(pattern, source.read_text(encoding="utf-8"), re.M), f"{path}::{name}"
