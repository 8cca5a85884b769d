// The dashboard's text helpers (clients/hmi/dom.js): a KPI tile's time says its unit.
import { test } from "node:test";
import assert from "node:assert/strict";

import { duration, span } from "../../../clients/hmi/dom.js";

test("a span carries its unit, from seconds to days", () => {
  assert.equal(span(52), "52 s");
  assert.equal(span(89.4), "89 s");
  assert.equal(span(90), "2 min");
  assert.equal(span(14 * 60 + 20), "14 min");
  assert.equal(span(3.5 * 3600), "3.5 h");
  assert.equal(span(3 * 86400), "3.0 d");
});

test("no figure is shown as a span", () => {
  for (const value of [null, undefined, NaN, Infinity, "52"]) assert.equal(span(value), "—");
  assert.equal(span(-3), "0 s");
});

test("a duration stays the clock-like time in a state", () => {
  assert.equal(duration(52), "00:52");
  assert.equal(duration(3725), "1:02:05");
});
