// The Trends card's geometry and captions: `node --test tests/unit/hmi/`.
import assert from "node:assert/strict";
import test from "node:test";

import { chartGeometry, trendCaption } from "../../../clients/hmi/trends.js";

const chart = (values, extra = {}) => ({
  figure: "glue_volume_percent", label: "glue volume", unit: "% of expected",
  centre: 100, lower: 95, upper: 105, drift: null,
  points: values.map((value, i) => ({ run_id: `r${i}`, at: i, good: value > 90, value })),
  ...extra,
});

test("the band holds the limits and every point, a lower value sits lower", () => {
  const shape = chartGeometry(chart([100, 101, 99, 80]), 200, 50);
  assert.equal(shape.points.length, 4);
  assert.ok(shape.upper < shape.centre && shape.centre < shape.lower); // SVG y grows down
  for (const p of shape.points) assert.ok(p.y >= 0 && p.y <= 50 && p.x >= 0 && p.x <= 200);
  assert.ok(shape.points[3].y > shape.lower); // the clogged part is below the band
  assert.equal(shape.points[3].good, false);
  assert.ok(shape.points[0].x < shape.points[3].x);
});

test("a chart without limits yet, and an empty one", () => {
  const early = chartGeometry(chart([100], { centre: null, lower: null, upper: null }));
  assert.equal(early.centre, null);
  assert.equal(early.points.length, 1);
  assert.deepEqual(chartGeometry(chart([], { centre: null, lower: null, upper: null })).points, []);
});

test("the caption names the drift, else the latest value against the limits", () => {
  const drifting = trendCaption(chart([100, 90], {
    drift: { direction: "down", rule: "8 parts in a row below the centre line" },
  }));
  assert.equal(drifting.drift, true);
  assert.equal(drifting.text, "drifting down: 8 parts in a row below the centre line");
  const steady = trendCaption(chart([100.4]));
  assert.equal(steady.text, "100 % of expected · limits 95.0 to 105");
});
