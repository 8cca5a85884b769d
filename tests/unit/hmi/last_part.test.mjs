// What the Last part card says of a run record: `node --test tests/unit/hmi/`.
// The verdict and its words are the server's (`part` of GET /operations' row); the
// card shows them as they are and adds the inspection's figures.
import assert from "node:assert/strict";
import test from "node:test";

import { describePart } from "../../../clients/hmi/last_part.js";

const GAP = "segment 3: a gap of 14.2 mm without bead (at most 3.0 mm)";

test("no run yet, a run nobody inspected, a run that did not complete", () => {
  assert.equal(describePart(null).label, "no part yet");
  const plain = describePart({
    run_id: "r1",
    outcome: "completed",
    result: { waypoints: 9 },
    part: {
      verdict: "not_inspected",
      inspected: false,
      reasons: ["not inspected (inspection_enabled is off)"],
      label: "not inspected (inspection_enabled is off)",
    },
  });
  assert.equal(plain.verdict, "not_inspected");
  assert.equal(plain.label, "not inspected (inspection_enabled is off)");
  assert.deepEqual(plain.figures, []);
  assert.equal(plain.note, "run completed");
  // A run that did not complete left a defective part, as every path counts it.
  const stopped = describePart({
    run_id: "r2",
    outcome: "failed",
    result: null,
    error: "EMERGENCY_STOP",
    part: {
      verdict: "defective",
      inspected: false,
      reasons: ["run stopped: emergency stop (STOP)"],
      label: "defective (not inspected)",
    },
  });
  assert.equal(stopped.verdict, "defective");
  assert.equal(stopped.label, "defective (not inspected)");
  assert.deepEqual(stopped.reasons, ["run stopped: emergency stop (STOP)"]);
  assert.equal(stopped.note, "run failed");
  // A row without the server's verdict shows none rather than guess one.
  const bare = describePart({ run_id: "r5", outcome: "completed", result: {} });
  assert.deepEqual([bare.verdict, bare.label], ["none", "no verdict"]);
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
  const part = describePart({
    run_id: "r3",
    outcome: "completed",
    result: { inspection },
    part: { verdict: "defective", inspected: true, reasons: [GAP], label: "defective" },
  });
  assert.equal(part.verdict, "defective");
  assert.equal(part.label, "defective");
  assert.deepEqual(part.reasons, [GAP]);
  assert.deepEqual(part.figures[0], ["path deviation p95", "0.74 mm"]);
  assert.deepEqual(part.figures[1], ["flow CV", "—"]); // not measured
  assert.equal(part.image, true);
});
