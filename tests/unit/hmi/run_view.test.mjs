// The run page's helpers (clients/hmi/run_view.js): series, spans, the replay's sample.
import assert from "node:assert/strict";
import { test } from "node:test";

import { extent, openSpans, pathSegments, polylines, sampleAt } from "../../../clients/hmi/run_view.js";

const samples = [
  { time: 0, x_mm: 0, y_mm: 0, valve_open: false, flow_ml_min: 0, speed_mm_s: null },
  { time: 1, x_mm: 10, y_mm: 0, valve_open: true, flow_ml_min: 10, speed_mm_s: 10 },
  { time: 2, x_mm: 20, y_mm: 0, valve_open: true, flow_ml_min: 12, speed_mm_s: 10 },
  { time: 3, x_mm: 20, y_mm: 5, valve_open: false, flow_ml_min: 0, speed_mm_s: 5 },
];

test("the valve's open spans end at the first sample that saw it closed", () => {
  assert.deepEqual(openSpans(samples), [[1, 3]]);
  assert.deepEqual(openSpans([{ time: 4, valve_open: true }, { time: 5, valve_open: true }]), [[4, 5]]);
  assert.deepEqual(openSpans([]), []);
});

test("the replay shows the last sample taken at or before its time", () => {
  assert.equal(sampleAt(samples, -1), 0);
  assert.equal(sampleAt(samples, 1.5), 1);
  assert.equal(sampleAt(samples, 3), 3);
  assert.equal(sampleAt(samples, 99), 3);
});

test("a missing value breaks a series' line; a flat series is widened, none is null", () => {
  assert.equal(polylines(samples, "speed_mm_s", 0, 3, 300, 100).length, 1);
  assert.deepEqual(polylines(samples, "flow_ml_min", 0, 3, 300, 100)[0].split(" ")[0], "0.0,100.0");
  assert.deepEqual(extent([3, 3, null]), [2, 4]);
  assert.equal(extent([null, undefined]), null);
});

test("the path is cut where the valve changes, each piece joined to the last", () => {
  const segments = pathSegments(samples);
  assert.deepEqual(segments.map((s) => s.open), [false, true, false]);
  assert.deepEqual(segments[1].points, [[0, 0], [10, 0], [20, 0]]);
  assert.deepEqual(segments[2].points, [[20, 0], [20, 5]]);
});
