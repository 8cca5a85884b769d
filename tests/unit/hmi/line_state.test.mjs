// The line view's reading of the cells' MQTT topics (clients/hmi/line_state.js).
import assert from "node:assert/strict";
import { test } from "node:test";

import { applyMessage, shownProgress, sortedRows, splitTopic, stopReasonText } from "../../../clients/hmi/line_state.js";

const state = (extra) => JSON.stringify({ cell_id: "c", state: "IDLE", since: 1, stop_reason: null, run_id: null, workpiece_id: null, ...extra });

test("only a cell's four topics under the prefix are read", () => {
  assert.deepEqual(splitTopic("glue", "glue/cell-1/state"), { cellId: "cell-1", kind: "state" });
  assert.equal(splitTopic("glue", "glue/cell-1/event"), null);
  assert.equal(splitTopic("glue", "other/cell-1/state"), null);
  assert.equal(splitTopic("glue", "glue/cell-1/state/x"), null);
  assert.equal(splitTopic("glue", "glue//state"), null);
});

test("status online and the last will's offline", () => {
  const line = new Map();
  assert.ok(applyMessage(line, "glue", "glue/a/status", JSON.stringify({ cell_id: "a", status: "online", time: 5, clean: true })));
  assert.equal(line.get("a").online, true);
  applyMessage(line, "glue", "glue/a/status", JSON.stringify({ cell_id: "a", status: "offline", time: null, clean: false }));
  assert.equal(line.get("a").online, false);
  applyMessage(line, "glue", "glue/a/status", "{not json");
  assert.equal(line.get("a").online, null);
});

test("a cell of an earlier release: the bare word", () => {
  const line = new Map();
  applyMessage(line, "glue", "glue/a/status", "online");
  assert.equal(line.get("a").online, true);
  applyMessage(line, "glue", "glue/a/status", "offline");
  assert.equal(line.get("a").online, false);
});

test("state, stop reason and OEE", () => {
  const line = new Map();
  applyMessage(line, "glue", "glue/a/state", state({ state: "ERROR", stop_reason: { code: "ROBOT_FAULT", message: "arm stopped" } }));
  applyMessage(line, "glue", "glue/a/kpis", JSON.stringify({ oee: { oee: 0.75, availability: 1 } }));
  const row = line.get("a");
  assert.equal(row.state, "ERROR");
  assert.equal(stopReasonText(row.stopReason), "ROBOT_FAULT: arm stopped");
  assert.equal(row.oee, 0.75);
  applyMessage(line, "glue", "glue/a/kpis", JSON.stringify({ oee: { oee: null } }));
  assert.equal(line.get("a").oee, null);
});

test("progress is shown only while the state names its run", () => {
  const line = new Map();
  applyMessage(line, "glue", "glue/a/state", state({ state: "EXECUTING_TRAJECTORY", run_id: "r1" }));
  applyMessage(line, "glue", "glue/a/progress", JSON.stringify({ run_id: "r1", waypoint: 3, total: 10, fraction: 0.3 }));
  assert.equal(shownProgress(line.get("a")).fraction, 0.3);
  applyMessage(line, "glue", "glue/a/state", state({ state: "IDLE", run_id: null }));
  assert.equal(shownProgress(line.get("a")), null);
});

test("unreadable payloads change nothing; rows come sorted", () => {
  const line = new Map();
  assert.equal(applyMessage(line, "glue", "glue/b/state", "{not json"), false);
  assert.equal(applyMessage(line, "glue", "glue/b/kpis", "[1]"), false);
  applyMessage(line, "glue", "glue/b/status", "online");
  applyMessage(line, "glue", "glue/a/status", "online");
  assert.deepEqual(sortedRows(line).map((r) => r.cellId), ["a", "b"]);
});
