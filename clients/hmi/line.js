/* The line view: every cell's state, stop reason, progress and OEE, live from the plant's
 * MQTT broker (its WebSocket listener) with the vendored MQTT.js. Where the broker is comes
 * from the line view's server (/line-config.json); the page trusts the broker's retained
 * messages and a dead cell's last will, so a cell that is down reads "offline". */
import mqtt from "./vendor/mqtt-5.16.0/mqtt.esm.js";
import { element, percent } from "./dom.js";
import { applyMessage, shownProgress, sortedRows, stopReasonText } from "./line_state.js";

const line = new Map();
const cards = new Map();
const decoder = new TextDecoder();

function card(cellId) {
  let node = cards.get(cellId);
  if (node) return node;
  node = element("section", "cell");
  node.dataset.cell = cellId;
  const head = element("div", "cell-head");
  head.append(element("span", "cell-id", cellId), element("span", "link", "?"));
  const facts = element("dl", "facts");
  for (const [term, key] of [["stop reason", "stop"], ["run", "run"], ["progress", "progress"], ["OEE", "oee"]]) {
    const value = element("dd", key, "—");
    facts.append(element("dt", "", term), value);
  }
  const bar = element("div", "bar");
  bar.append(element("span"));
  node.append(head, element("div", "state", "—"), facts, bar);
  cards.set(cellId, node);
  return node;
}

function render(row) {
  const node = card(row.cellId);
  const online = row.online === null ? "unknown" : String(row.online);
  node.dataset.online = online;
  const link = node.querySelector(".link");
  link.dataset.online = online;
  link.textContent = row.online === null ? "?" : row.online ? "online" : "offline";
  const state = node.querySelector(".state");
  state.textContent = row.state ?? "—";
  state.dataset.state = row.state ?? "";
  state.dataset.stale = String(row.online === false);  // the last state it published
  state.title = row.online === false ? "last state before the cell went offline" : "";
  node.querySelector(".stop").textContent = stopReasonText(row.stopReason) || "—";
  node.querySelector(".run").textContent = row.runId ?? "—";
  const progress = shownProgress(row);
  const pct = progress && typeof progress.fraction === "number" ? 100 * progress.fraction : null;
  node.querySelector(".progress").textContent = progress
    ? `${pct === null ? "—" : pct.toFixed(0)} % (${progress.waypoint}/${progress.total})` : "—";
  node.querySelector(".bar > span").style.width = `${pct === null ? 0 : Math.min(100, Math.max(0, pct))}%`;
  node.querySelector(".oee").textContent = percent(row.oee);
}

function renderAll() {
  const main = document.getElementById("cells");
  document.getElementById("no-cells").hidden = line.size > 0;
  for (const row of sortedRows(line)) {
    render(row);
    main.append(card(row.cellId));  // keeps the cards in the order of their ids
  }
}

function showBroker(text, connected) {
  const node = document.getElementById("broker");
  node.textContent = text;
  node.dataset.connected = String(connected);
}

async function main() {
  const config = await (await fetch("/line-config.json")).json();
  const client = mqtt.connect(config.broker, {
    clientId: `line-view-${Math.random().toString(16).slice(2, 10)}`,
    keepalive: 30, reconnectPeriod: 2000, connectTimeout: 10000, clean: true,
    // Plain timers: MQTT.js's default starts a Worker from a blob: URL, which the page's
    // Content-Security-Policy (script-src 'self', as the dashboard's) refuses. A hidden
    // tab's slowed timers may then miss a ping: the view reconnects and rereads the
    // retained state.
    timerVariant: "native",
  });
  client.on("connect", () => {
    showBroker(`broker ${config.broker} · prefix ${config.prefix}`, true);
    client.subscribe(`${config.prefix}/+/+`, { qos: 0 });
  });
  client.on("reconnect", () => showBroker(`reconnecting to ${config.broker}…`, false));
  client.on("offline", () => showBroker(`broker ${config.broker} unreachable: values may be old`, false));
  client.on("message", (topic, payload) => {
    if (applyMessage(line, config.prefix, topic, decoder.decode(payload))) renderAll();
  });
}

main().catch((error) => showBroker(`line view: ${error}`, false));
