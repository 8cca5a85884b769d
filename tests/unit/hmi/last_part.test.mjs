// What the Last part card says of a run record: `node --test tests/unit/hmi/`.
import assert from "node:assert/strict";
import test from "node:test";

import { describePart } from "../../../clients/hmi/last_part.js";

const GAP = "segment 3: a gap of 14.2 mm without bead (at most 3.0 mm)";

test("no run yet, and a run nobody inspected", () => {
  assert.equal(describePart(null).label, "no part yet");
  const plain = describePart({ run_id: "r1", outcome: "completed", result: { waypoints: 9 } });
  assert.equal(plain.verdict, "none");
  assert.equal(plain.label, "not inspected");
  assert.deepEqual(plain.reasons, []);
  // A run that did not complete left a defective part, as the order card counts it.
  const failed = describePart({ run_id: "r2", outcome: "failed", result: null, error: "jam" });
  assert.equal(failed.verdict, "defective");
  assert.equal(failed.label, "defective (not inspected)");
  assert.deepEqual(failed.reasons, ["run failed: jam"]);
  assert.equal(failed.note, "run failed");
  const stopped = describePart({ run_id: "r6", outcome: "cancelled", result: null });
  assert.deepEqual([stopped.verdict, stopped.reasons], ["defective", ["run cancelled"]]);
  // A full disk took the inspection's image: the run says why it was not inspected.
  const full = describePart({
    run_id: "r5", outcome: "completed", result: { waypoints: 9, not_inspected: "no space" },
  });
  assert.equal(full.label, "not inspected (no space)");
  assert.equal(full.note, "run completed");
});

test("a defective part: its reasons, its figures, whether an image was kept", () => {
  const inspection = {
    verdict: "defective",
    reasons: [GAP],
    precision_p95_mm: 0.736,
    dispensing_cv_percent: null,
    glue_ml: 1.35,
    vision_residual_mm: 0.18,
    image: true,
  };
  const part = describePart({ run_id: "r3", outcome: "completed", result: { inspection } });
  assert.equal(part.verdict, "defective");
  assert.deepEqual(part.reasons, [GAP]);
  assert.deepEqual(part.figures[0], ["path deviation p95", "0.74 mm"]);
  assert.deepEqual(part.figures[1], ["flow CV", "—"]); // not measured
  assert.equal(part.image, true);
  // A verdict outside the contract is not shown as one.
  const odd = describePart({ run_id: "r4", outcome: "completed", result: { inspection: { verdict: "?" } } });
  assert.equal(odd.label, "not inspected");
});
