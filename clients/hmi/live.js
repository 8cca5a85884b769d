/* The live connection: GET a one-shot ticket (POST /ws-ticket), open /ws with it,
 * apply the snapshot, then every message. When the socket drops, the state on
 * screen is marked stale (not live) and the page reconnects with backoff; the
 * new snapshot is the truth again. A gap in `seq` means a message was missed:
 * the page resynchronises from GET /state. */

import { AuthError, api, errorText, getJson } from "./api.js";
import { refreshLastPart } from "./last_part.js";
import { applyDeviceSample, refreshLibrary, refreshPanels } from "./panels.js";
import {
  applyIfNewer,
  applyState,
  renderProgress,
  setLive,
  showBanner,
  showMessage,
  startProgress,
  updateProgress,
} from "./render.js";
import {
  ENDINGS,
  hmi,
  isOperational,
  LIVE_TYPES,
  RECONNECT_FIRST_MS,
  RECONNECT_MAX_MS,
  WATCHDOG_DEAD_MS,
  WATCHDOG_PING_MS,
} from "./store.js";
import {
  drawTrajectory,
  forgetRuns,
  refreshCalibration,
  refreshFrame,
  refreshTrajectory,
} from "./trajectory.js";

export async function connect() {
  clearTimeout(hmi.reconnectTimer);
  hmi.reconnectTimer = null;
  let ticket;
  try {
    const response = await api("POST", "/ws-ticket");
    if (!response.ok) throw new Error(`no ticket: ${await errorText(response)}`);
    ticket = (await response.json()).ticket;
  } catch (error) {
    if (error instanceof AuthError) return;
    const unreachable = error instanceof TypeError; // fetch: no answer at all
    scheduleReconnect(unreachable ? "the server cannot be reached" : error.message);
    return;
  }
  if (!hmi.token) return;
  const scheme = location.protocol === "https:" ? "wss" : "ws";
  const query = `ticket=${encodeURIComponent(ticket)}&types=${LIVE_TYPES.join(",")}`;
  const ws = new WebSocket(`${scheme}://${location.host}/ws?${query}`);
  hmi.ws = ws;
  hmi.lastMessageMs = performance.now();
  ws.onmessage = (event) => hmi.ws === ws && onMessage(JSON.parse(event.data));
  ws.onclose = (event) => {
    if (hmi.ws !== ws) return;
    hmi.ws = null;
    scheduleReconnect(closeReason(event));
  };
}

function closeReason(event) {
  const known = {
    1001: "the server is shutting down",
    1006: "the connection dropped",
    1013: "the server has too many clients",
    4001: "the server dropped this client (it fell behind)",
    4401: "the server refused the ticket",
  };
  const text = event.reason || known[event.code] || "the connection closed";
  return `${text} (code ${event.code})`;
}

/** Close the socket at once, without waiting for a closing handshake. */
export function dropSocket(reason) {
  const ws = hmi.ws;
  hmi.ws = null;
  if (ws) {
    ws.onmessage = null;
    ws.onclose = null;
    ws.close();
  }
  if (reason) scheduleReconnect(reason);
}

function scheduleReconnect(reason) {
  if (!hmi.token) return;
  if (hmi.live) hmi.counters.disconnects += 1;
  setLive(false, "connection lost");
  hmi.attempts += 1;
  const base = Math.min(RECONNECT_MAX_MS, RECONNECT_FIRST_MS * 2 ** (hmi.attempts - 1));
  const delay = Math.round(base * (0.8 + Math.random() * 0.4));
  showBanner(`${reason}. Attempt ${hmi.attempts}, next try in ${(delay / 1000).toFixed(1)} s.`);
  clearTimeout(hmi.reconnectTimer);
  hmi.reconnectTimer = setTimeout(connect, delay);
}

/** Half-open connections: ping after silence, give up after a long one. */
export function watchdog() {
  if (!hmi.ws || !hmi.live) return;
  const silent = performance.now() - hmi.lastMessageMs;
  if (silent > WATCHDOG_DEAD_MS) dropSocket("no answer from the server");
  else if (silent > WATCHDOG_PING_MS) hmi.ws.send(JSON.stringify({ type: "ping" }));
}

function onMessage(message) {
  hmi.lastMessageMs = performance.now();
  hmi.counters.messages += 1;
  if (message.type === "snapshot") return onSnapshot(message);
  if (message.type === "device") return applyDeviceSample(message); // a sample: no seq
  if (typeof message.seq === "number") checkSequence(message.seq);
  if (message.type === "state_changed") onStateChanged(message);
  else if (message.type === "progress") onProgress(message);
  else if (message.type === "error") onFault(message);
  else if (message.type === "alert") onAlert(message);
}

function onSnapshot(snapshot) {
  const restarted = hmi.boot !== null && snapshot.boot !== hmi.boot;
  hmi.boot = snapshot.boot;
  if (restarted) {
    // The server restarted: the run, the plan and the frame on screen are of its last life.
    hmi.progress = null;
    forgetRuns();
    refreshCalibration();
  }
  hmi.lastSeq = snapshot.seq;
  hmi.attempts = 0;
  hmi.counters.connects += 1;
  const progress = snapshot.operation && snapshot.operation.progress;
  if (snapshot.operation) startProgress(snapshot.operation.name, snapshot.operation.run_id);
  else if (hmi.progress && !hmi.progress.ended) hmi.progress.ended = "ended";
  if (progress) updateProgress(progress);
  setLive(true);
  applyState(snapshot);
  refreshPanels(true);
  refreshTrajectory();
  refreshFrame(); // one may have been captured, or the server forgot it, while not live
  refreshLastPart(); // a run may have ended while not live
}

/** seq rises by one; a gap means something was missed: resynchronise from GET /state. */
function checkSequence(seq) {
  if (hmi.lastSeq !== null && seq !== hmi.lastSeq + 1) {
    hmi.counters.gaps += 1;
    getJson("/state").then(applyIfNewer).catch(() => {});
  }
  hmi.lastSeq = seq;
}

function onStateChanged(message) {
  const { old_state: from, new_state: to, event } = message;
  if (isOperational(to) && !isOperational(from) && to !== "PAUSED") startProgress(to, null);
  if (!isOperational(to) && hmi.progress && !hmi.progress.ended) {
    hmi.progress.ended = ENDINGS[event] || event.toLowerCase();
  }
  applyState(message.snapshot);
  if (isOperational(to) && !message.snapshot.operation) {
    // The snapshot that enters a run's state is taken before the run starts, so it names
    // none (the state card showed no run until the page was reloaded): ask once it has.
    getJson("/state").then(applyIfNewer).catch(() => {});
  }
  refreshPanels(true); // link figures and faults; `device` messages carry the readings
  setTimeout(refreshPanels, 1000); // KPIs and history settle a moment after a transition
  if (from === "CALIBRATING_ROBOT" || from === "CALIBRATING_CAMERA") refreshCalibration();
  if (isOperational(from) && !isOperational(to)) {
    refreshFrame(); // it may have taken a picture
    refreshLastPart(); // a run ended: its part's verdict (its record is committed by now)
  }
  if (from === "CREATING_WORKPIECE") {
    refreshLibrary();
    if (to === "IDLE") hmi.onWorkpieceCreated(message.snapshot.operation_result);
  }
}

function onProgress(message) {
  if (message.recovery_attempt) {
    const outcome = message.recovered ? "recovered" : "failed";
    showMessage("info", `recovery attempt ${message.recovery_attempt} (${message.cause}): ${outcome}`);
    return;
  }
  if (!hmi.progress || hmi.progress.run_id !== message.run_id) {
    startProgress(message.operation, message.run_id);
  }
  updateProgress(message);
  // A new run, or this run not planned yet when last asked (its plan comes after its
  // first progress messages): ask again.
  const shown = hmi.trajectory;
  const stale = shown?.run_id !== message.run_id || shown?.planned === false;
  if (message.operation === "trajectory" && stale) refreshTrajectory();
  renderProgress();
  drawTrajectory();
}

function onFault(fault) {
  showMessage("error", `fault ${fault.code} (${fault.component}): ${fault.message}`, "reset");
}

function onAlert(alert) {
  showMessage("error", `alert: ${alert.message}`);
}

/** Test and maintenance hook: close the socket as if the network dropped it. */
export function dropConnection() {
  dropSocket("closed by the page");
}
