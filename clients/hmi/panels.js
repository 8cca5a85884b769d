/* The panels refreshed every few seconds and on each change: devices (health),
 * KPIs, history; and the workpiece library, refreshed when a workpiece was made.
 * While the WebSocket is live the devices card is not polled: GET /health once on
 * each snapshot and change of state, and `device` messages (valve, flow, pressure,
 * robot pose; every 0.1 s during a run) update it in between. A 3 s poll missed a
 * valve opened between two polls and showed "closed" while glue flowed. */

import { AuthError, blobUrl, getJson } from "./api.js";
import { $, clockTime, duration, element, facts, number, percent, span } from "./dom.js";
import { refreshMaintenance } from "./maintenance.js";
import { refreshOrders } from "./orders.js";
import { HISTORY_ROWS, hmi, STATE_TONE } from "./store.js";

let refreshing = false;
let refreshAgain = false;
let healthAgain = false;

/** KPIs and history, and health when asked or not live; a request during a
 * refresh runs once it is done. */
export async function refreshPanels(withHealth = !hmi.live) {
  if (!hmi.token) return;
  healthAgain = healthAgain || withHealth;
  if (refreshing) {
    refreshAgain = true;
    return;
  }
  refreshing = true;
  try {
    do {
      refreshAgain = false;
      const health = healthAgain;
      healthAgain = false;
      await Promise.all([
        health ? panel("card-health", "/health", renderHealth) : null,
        panel("card-kpis", "/kpis", renderKpis),
        panel("card-history", `/history?limit=${HISTORY_ROWS}`, renderHistory),
        refreshOrders(),
        refreshMaintenance(),
      ]);
    } while (refreshAgain && hmi.token);
  } finally {
    refreshing = false;
  }
}

/** A `device` message: the live readings merged into the last health shown. */
export function applyDeviceSample(sample) {
  const health = hmi.health;
  if (!health) return; // the first GET /health (on the snapshot) has not answered yet
  for (const name of ["glue", "robot"]) {
    const { age_ms: _age, ...readings } = sample[name] || {};
    if (health.devices[name]) Object.assign(health.devices[name], readings);
  }
  const connected = Object.values(health.devices).every((device) => device.connected);
  health.status = connected ? "ok" : "degraded";
  renderHealth(health);
  document.querySelector(".card-health").dataset.stale = "false";
}

async function panel(cardClass, path, render) {
  const card = document.querySelector(`.${cardClass}`);
  try {
    render(await getJson(path));
    card.dataset.stale = "false";
  } catch {
    card.dataset.stale = "true";
  }
}

// --- devices, KPIs, history -------------------------------------------------

function renderHealth(health) {
  hmi.health = health;
  const status = $("health-status");
  status.textContent = health.status;
  status.dataset.kind = health.status === "ok" ? "ok" : "fault";
  const devices = $("devices");
  const note = journalNote(health.journal);
  devices.replaceChildren(
    ...["robot", "glue", "camera"]
      .filter((name) => health.devices[name])
      .map((name) => deviceCard(name, health.devices[name])),
    ...(note ? [note] : []),
  );
}

/** The journal, shown only when something is wrong with it: a write failing now (no
 * command but STOP is accepted until it writes again), or damage start-up found. */
function journalNote(journal) {
  if (!journal) return null;
  const problems = [];
  if (journal.last_error) problems.push(`not writing: ${journal.last_error}`);
  for (const damage of journal.damage || []) problems.push(`damaged: ${damage.message}`);
  if (!problems.length) return null;
  const card = element("div", "device journal");
  card.dataset.device = "journal";
  const state = element("span", "pill", journal.last_error ? "not writing" : "damaged");
  state.dataset.kind = "fault";
  const head = element("div", "device-head");
  head.append(element("span", "device-name", "journal"), state);
  card.append(head, ...problems.map((text) => element("div", "device-error", text)));
  return card;
}

function deviceCard(name, device) {
  const card = element("div", "device");
  card.dataset.device = name;
  card.dataset.connected = String(device.connected);
  if (name === "glue") card.dataset.valve = device.valve_open ? "open" : "closed";
  const state = element("span", "pill", device.connected ? "connected" : "disconnected");
  state.dataset.kind = device.connected ? "ok" : "fault";
  const head = element("div", "device-head");
  head.append(element("span", "device-name", name), state);
  card.append(head, facts(deviceFacts(name, device)));
  if (device.last_error) card.append(element("div", "device-error", device.last_error));
  return card;
}

function deviceFacts(name, device) {
  const rtt = device.last_rtt_ms == null ? "—" : `${number(device.last_rtt_ms, 1)} ms`;
  const rows = [["round trip", rtt]];
  if (name === "robot") {
    const pose = Array.isArray(device.position) ? device.position : [];
    const where = pose.length >= 3 ? pose.slice(0, 3).map((v) => number(v, 1)).join(", ") : "—";
    rows.push(
      ["position", pose.length >= 3 ? `${where} mm` : where],
      ["link losses", String(device.connection_losses ?? "—")],
      ["reconnects", String(device.reconnects ?? "—")],
    );
  } else if (name === "glue") {
    const alarms = (device.alarms || []).join(", ");
    rows.push(
      ["flow", `${number(device.flow_ml_min, 1)} ml/min`],
      ["pressure", `${number(device.pressure_psi, 1)} psi`],
      ["temperature", `${number(device.temperature_c, 1)} °C`],
      ["valve", device.valve_open ? "OPEN" : "closed", device.valve_open ? "on" : ""],
      ["alarms", alarms || "none", alarms ? "alarm" : ""],
    );
  } else if (name === "camera") {
    rows.push(["resolution", device.resolution || "—"], ["mode", device.mode || "—"]);
  }
  return rows;
}

function renderKpis(kpis) {
  const oee = kpis.oee || {};
  const quality = kpis.quality || {};
  const figures = [
    ["OEE", percent(oee.oee)],
    ["Availability", percent(oee.availability)],
    ["Utilization", percent(kpis.utilization)],
    ["Workpieces", String(kpis.workpieces_processed ?? "—"), "workpieces completed",
      "workpieces sprayed by completed runs"],
    ["Quality", percent(oee.quality), "quality", "good parts / good and defective parts"],
    // The part counts use the words of the order card and the Last part card.
    ["Good", String(quality.parts_good ?? "—"), "good parts", "parts inspected and judged good"],
    ["Defective", String(quality.parts_defective ?? "—"), "defective parts",
      "parts judged defective, or whose run did not complete (not inspected)"],
    ["Not inspected", String(quality.parts_not_inspected ?? "—"), "parts not inspected",
      "parts sprayed whole that nobody inspected"],
    ["Operations", String(kpis.operations_completed ?? "—"), "operations completed",
      "runs and calibrations that completed"],
    ["MTBF", kpis.mtbf_s == null ? "—" : span(kpis.mtbf_s), "MTBF", "mean time between failures"],
    ["MTTR", kpis.mttr_s == null ? "—" : span(kpis.mttr_s), "MTTR", "mean time to repair (in ERROR)"],
    ["Errors", String(kpis.errors_counted ?? "—"), "errors", "faults that stopped the cell"],
  ];
  $("kpis").replaceChildren(
    ...figures.map(([name, value, label = name, meaning = ""]) => {
      const tile = element("div", "kpi");
      tile.dataset.kpi = name.toLowerCase();
      if (meaning) tile.title = meaning;
      tile.append(element("div", "kpi-value", value), element("div", "kpi-label", label));
      return tile;
    }),
  );
  $("kpi-window").textContent = kpis.window ? `last ${number(kpis.window.hours, 0)} h` : "";
}

function renderHistory(page) {
  const rows = (page.transitions || []).slice(0, HISTORY_ROWS).map((t) => {
    const row = document.createElement("tr");
    for (const [text, cls] of [
      [clockTime(t.time), ""],
      [t.old_state, `tone-${STATE_TONE[t.old_state] || "init"}`],
      [t.new_state, `tone-${STATE_TONE[t.new_state] || "init"}`],
      [t.event, ""],
      [duration(t.time_in_old_state), "num"],
    ]) {
      row.append(breakable(element("td", cls), text));
    }
    return row;
  });
  $("history").replaceChildren(...rows);
}

/** `text` in `cell`, with a line break allowed after each underscore (OPERATION_<wbr>COMPLETED):
 * a narrow column wraps a name where it reads well, and copies it unchanged. */
function breakable(cell, text) {
  const parts = String(text).split("_");
  parts.forEach((part, i) => {
    if (i > 0) cell.append("_", document.createElement("wbr"));
    cell.append(part);
  });
  return cell;
}

// --- workpiece library ------------------------------------------------------

export async function refreshLibrary() {
  try {
    const { workpieces } = await getJson("/workpieces");
    const urls = await Promise.all(
      workpieces.map((w) => (w.has_thumbnail ? blobUrl(`/workpieces/${encodeURIComponent(w.id)}/thumbnail`) : null)),
    );
    hmi.thumbnails.forEach((url) => URL.revokeObjectURL(url));
    hmi.thumbnails = urls.filter(Boolean);
    $("library").replaceChildren(...workpieces.map((w, i) => workpieceCard(w, urls[i])));
    $("library-count").textContent = `${workpieces.length} in the library`;
  } catch (error) {
    if (!(error instanceof AuthError)) $("library-count").textContent = "library unavailable";
  }
}

function workpieceCard(workpiece, url) {
  const card = element("figure", "workpiece");
  card.dataset.workpiece = workpiece.id;
  const picture = url ? document.createElement("img") : element("div", "no-thumb", "no image");
  if (url) {
    picture.src = url;
    picture.alt = `thumbnail of ${workpiece.name}`;
  }
  const spray = workpiece.spray || {};
  const caption = element("figcaption");
  caption.append(
    element("strong", "", workpiece.name),
    element("span", "muted small", `${workpiece.id} · fill ${spray.fill || "—"} · ${spray.speed_mm_s ?? "—"} mm/s`),
  );
  card.append(picture, caption);
  return card;
}
