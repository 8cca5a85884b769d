// Whom the state card asks to call when the cell waits for a command the role lacks:
// `node --test tests/unit/hmi/`.
import assert from "node:assert/strict";
import test from "node:test";

import { callFor } from "../../../clients/hmi/role.js";

const NEEDS = { start: "operator", reset: "maintenance", estop: "viewer", home: "maintenance" };

function me(role, commands) {
  return { name: "line 3 HMI", role, needs: NEEDS, commands: new Set(commands), pages: {} };
}

test("an operator after a stop is told to call maintenance to reset", () => {
  const operator = me("operator", ["start", "estop"]);
  assert.equal(
    callFor(operator, ["reset", "estop"]),
    "Call maintenance to reset: needs the maintenance role",
  );
});

test("a role that may make the recovery is told nothing", () => {
  const maintenance = me("maintenance", ["start", "reset", "estop", "home"]);
  assert.equal(callFor(maintenance, ["reset", "estop"]), "");
  assert.equal(callFor(null, ["reset"]), "");
});
