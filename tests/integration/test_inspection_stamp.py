"""The inspection image's stamp says the part's verdict, through the real run: a part
judged defective on its glue volume (a partly clogged nozzle gives 60 % of the flow, under
the dispenser's own flow alarm as the test sets it, so the run completes) is stamped
DEFECTIVE, in red, on the image GET /runs/{run_id}/inspection.jpg serves, whatever its
bead's own findings."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from tests.rig import open_rig, run


async def test_a_part_defective_on_glue_volume_is_stamped_defective(tmp_path: Path) -> None:
    async with open_rig(tmp_path / "data", glue_flow_deviation_pct=50) as rig:
        rig.glue.clog_nozzle(0.6)
        snapshot = await run(rig, "start", {"workpiece_id": "demo"})
        assert snapshot["state"] == "IDLE", snapshot["error"]
        operations = await rig.api.get("/operations", params={"kind": "trajectory", "limit": 1})
        run_id = operations.json()["operations"][0]["run_id"]
        inspection = (await rig.api.get(f"/runs/{run_id}/inspection")).json()
        assert inspection["verdict"] == "defective", inspection["reasons"]
        assert any("glue dispensed" in r for r in inspection["reasons"]), inspection["reasons"]
        image = await rig.api.get(f"/runs/{run_id}/inspection.jpg")
        assert image.status_code == 200
        frame = cv2.imdecode(np.frombuffer(image.content, np.uint8), cv2.IMREAD_COLOR)
        corner = frame[15:60, 15:330].astype(int)
        blue, green, red = corner[..., 0], corner[..., 1], corner[..., 2]
        greens = int(((green > 150) & (red < 120) & (blue < 120)).sum())
        reds = int(((red > 180) & (green < 100) & (blue < 100)).sum())
        assert reds > 200 and reds > 5 * greens, (greens, reds)
