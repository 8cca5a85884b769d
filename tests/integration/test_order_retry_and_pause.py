"""Orders that never trap, on the simulated cell with a real server and journal: a retry
of POST /orders with the same Idempotency-Key gets the first order (after a restart
too), and a pause in an order's part is continued by the cell's Resume, part and order.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

from tests.integration.test_orders import order_of, wait_order, wait_running
from tests.rig import WAIT_S, open_rig

ORDER = {"workpiece_id": "demo", "quantity": 5}


async def test_a_retry_with_the_same_key_gets_the_first_order(tmp_path: Path) -> None:
    key = {"Idempotency-Key": "5d0c6f7e-order-of-line-3"}
    async with open_rig(tmp_path) as rig:
        first = await rig.api.post("/orders", json=ORDER, headers=key)
        assert first.status_code == 201, first.text
        order_id = first.json()["order"]["order_id"]
        again = await rig.api.post("/orders", json=ORDER, headers=key)
        assert again.status_code == 200, again.text
        assert again.json()["order"]["order_id"] == order_id
        other = await rig.api.post("/orders", json={**ORDER, "quantity": 6}, headers=key)
        assert other.status_code == 422, other.text
        assert "Idempotency-Key" in other.text and order_id in other.text
        assert len((await rig.api.get("/orders")).json()["orders"]) == 1
        assert (await rig.api.post(f"/orders/{order_id}/close")).status_code == 200
    async with open_rig(tmp_path, wait_idle=False) as rig:  # the key is on record
        after = await rig.api.post("/orders", json=ORDER, headers=key)
        assert after.status_code == 200, after.text
        assert after.json()["order"]["order_id"] == order_id
        assert after.json()["order"]["state"] == "closed"
        assert len((await rig.api.get("/orders")).json()["orders"]) == 1


async def test_resume_after_a_pause_continues_the_part_and_the_order(tmp_path: Path) -> None:
    # The card's flow, not the parts' verdicts: parts are not inspected here and count
    # toward the quantity.
    async with open_rig(tmp_path, inspection_enabled=False) as rig:
        created = await rig.api.post("/orders", json={"workpiece_id": "demo", "quantity": 2})
        assert created.status_code == 201, created.text
        order_id = created.json()["order"]["order_id"]
        await wait_running(rig)
        assert (await rig.api.post("/pause")).status_code == 202
        await rig.wait_state("PAUSED")
        async with asyncio.timeout(WAIT_S):
            while "paused" not in str((order := await order_of(rig, order_id))["reason"]):
                await asyncio.sleep(0.05)
        assert order["state"] == "running", order
        assert (await rig.api.post("/resume")).status_code == 202
        order = await wait_order(rig, order_id, "completed", "held")
        assert order["state"] == "completed", order
        assert (order["not_inspected"], order["counted"], order["parts_made"]) == (2, 2, 2), order
