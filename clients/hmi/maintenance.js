/* The Maintenance card: each maintenance item's state, the adhesive's pot life and the
 * glue level, from GET /maintenance (viewer), refreshed with the other panels. An item
 * due or overdue, a pot life near its end or past it, and a low level are marked as a
 * warning, so a technician sees what needs doing without reading every figure. Marking
 * an item done and the refill are maintenance actions (gluectl maintenance, the API),
 * not buttons on a shared production panel. */

import { getJson } from "./api.js";
import { $, element, facts, span } from "./dom.js";

const WARN = new Set(["due", "overdue", "near", "expired", "low"]);

/** GET /maintenance into the card; the card is marked stale when it cannot be read. */
export async function refreshMaintenance() {
  const card = document.querySelector(".card-maintenance");
  if (!card) return;
  try {
    renderMaintenance(await getJson("/maintenance"));
    card.dataset.stale = "false";
  } catch {
    card.dataset.stale = "true";
  }
}

export function renderMaintenance(state) {
  const rows = (state.items || []).map((item) => [
    item.name,
    `${item.status} · ${item.percent.toFixed(0)} %`,
    WARN.has(item.status) ? "warn" : "",
  ]);
  const pot = state.pot_life || {};
  if (pot.status !== "off") {
    rows.push(["Pot life", pot.open_s == null ? "no glue yet" : `${pot.status} · open ${span(pot.open_s)}`,
      WARN.has(pot.status) ? "warn" : ""]);
  }
  const level = state.glue_level || {};
  if (level.status !== "off") {
    rows.push(["Glue level", `${level.level_ml.toFixed(0)} ml · ${level.percent.toFixed(0)} %`,
      WARN.has(level.status) ? "warn" : ""]);
  }
  const warned = rows.filter((row) => row[2] === "warn").length;
  const pill = $("maintenance-status");
  pill.textContent = warned ? `${warned} to do` : "ok";
  pill.dataset.kind = warned ? "warn" : "ok";
  const counters = state.counters || {};
  const wear = element(
    "div",
    "muted small",
    `${counters.parts ?? 0} parts · ${(counters.glue_ml ?? 0).toFixed(0)} ml · ` +
      `${counters.valve_cycles ?? 0} valve cycles`,
  );
  $("maintenance").replaceChildren(facts(rows), wear);
}
