"""Create-workpiece says when the part on the table is one the library holds already,
against the real server, simulated camera and library: which part and how well it
matches; asked to store only a new part (`if_new`), it stores nothing and says so."""

from __future__ import annotations

from pathlib import Path

from tests.rig import open_rig, run


async def test_a_copy_of_a_stored_part_is_named_and_not_stored_when_only_new_is_asked(
    tmp_path: Path,
) -> None:
    async with open_rig(tmp_path / "data") as rig:
        before = (await rig.api.get("/workpieces")).json()
        count = len(before["workpieces"])
        # The simulated table holds the demo part: asked for a new part only, nothing is
        # stored and the answer names demo, with how well the outlines agree.
        snapshot = await run(rig, "create-workpiece", {"name": "bracket", "if_new": True})
        assert snapshot["state"] == "IDLE", snapshot["error"]
        result = snapshot["operation_result"]
        assert result["stored"] is False, result
        assert result["similar"]["workpiece_id"] == "demo"
        assert result["similar"]["name"] == (await rig.api.get("/workpieces/demo")).json()["name"]
        assert result["similar"]["fit_error_mm"] < 2.0
        assert "demo" in result["message"]
        assert len((await rig.api.get("/workpieces")).json()["workpieces"]) == count
        # Told to store it anyway, it is stored under its name, the match still said.
        snapshot = await run(rig, "create-workpiece", {"name": "bracket"})
        result = snapshot["operation_result"]
        assert result["stored"] is True and result["name"] == "bracket", result
        assert result["similar"]["workpiece_id"] == "demo"
        assert len((await rig.api.get("/workpieces")).json()["workpieces"]) == count + 1
