/* The state box, the fault, the command buttons, the message line and the progress
 * bar: drawn from `hmi` (store.js), never from anything the page guessed. */

import { $, clockTime, duration } from "./dom.js";
import { callFor, roleAllows } from "./role.js";
import { hmi, STATE_TONE } from "./store.js";

// --- state ------------------------------------------------------------------

/** A state read over HTTP may race the socket: never step back to an older state. */
export function applyIfNewer(view) {
  if (!hmi.view || view.since >= hmi.view.since) applyState(view);
}

export function applyState(view) {
  hmi.view = view;
  if (!view.stop_reason) clearMessage("reset");
  if (view.state === "ERROR") clearMessage("stopped");
  // An answer describes the state it left the cell in: gone once the cell has left it.
  const box = $("message");
  if (box.dataset.clears?.startsWith("state:") && box.dataset.clears !== `state:${view.state}`) {
    clearMessage(box.dataset.clears);
  }
  hmi.enteredAtMs = performance.now() - (view.time_in_state || 0) * 1000;
  renderState();
  renderCommands();
  renderProgress();
}

/** Live only while the socket is up and its snapshot applied; otherwise greyed, "not live". */
export function setLive(live, text) {
  hmi.live = live;
  $("link").dataset.live = String(live);
  $("link-text").textContent = live ? "live" : text || "not live";
  $("state").dataset.stale = String(!live);
  $("app").dataset.live = String(live);
  if (live) {
    $("banner").hidden = true;
    stopNotDelivered();
  }
  renderCommands();
}

export function showBanner(detail) {
  $("banner-detail").textContent = detail;
  $("banner").hidden = false;
}

function renderState() {
  const view = hmi.view;
  if (!view) return;
  const box = $("state");
  box.dataset.state = view.state;
  box.dataset.tone = STATE_TONE[view.state] || "init";
  $("state-name").textContent = view.state.replaceAll("_", " ");
  $("state-previous").textContent = view.previous_state
    ? `from ${view.previous_state.replaceAll("_", " ")}`
    : "";
  const op = view.operation;
  $("state-operation").textContent = op ? `operation ${op.name} · run ${op.run_id}` : "";
  renderFault(view);
  tick();
}

function renderFault(view) {
  const reason = view.state === "ERROR" ? view.stop_reason || view.error : null;
  $("fault").hidden = !reason;
  if (!reason) return;
  // The recovery this role cannot make: whom to call, in words.
  const call = callFor(hmi.me, view.available_commands || []);
  $("fault-call").hidden = !call;
  $("fault-call").textContent = call;
  $("fault-message").textContent = reason.message;
  $("fault-meta").textContent =
    `${reason.code} · ${reason.component} · ${reason.classification} · ${clockTime(reason.time)}`;
  $("fault-action").textContent = reason.recommended_action || "—";
  const latest = view.error;
  const differs = latest && view.stop_reason && latest.event_id !== view.stop_reason.event_id;
  $("fault-latest").hidden = !differs;
  if (differs) $("fault-latest").textContent = `Latest fault: ${latest.code}: ${latest.message}`;
}

/** The clock, and the time in state: frozen while not live, as the state itself is. */
export function tick() {
  $("clock").textContent = new Date().toLocaleTimeString([], { hour12: false });
  if (!hmi.view || (!hmi.live && $("state-time").textContent !== "—")) return;
  const seconds = (performance.now() - hmi.enteredAtMs) / 1000;
  $("state-time").textContent = duration(seconds);
}

// --- commands and messages --------------------------------------------------

export function renderCommands() {
  const allowed = new Set((hmi.view && hmi.view.available_commands) || []);
  for (const button of document.querySelectorAll("[data-command]")) {
    const name = button.dataset.command;
    button.disabled =
      !hmi.live || !allowed.has(name) || !roleAllows(name) || hmi.pending.has(name);
  }
  if (hmi.view) renderFault(hmi.view);
  for (const hook of hmi.renderHooks) hook();
}

/** A command's answer in words (never its HTTP status). It describes the state the
 * cell was left in (`body.state`), so it goes once the cell has left that state. */
export function showAnswer(status, text, state) {
  const kind = status === 202 ? "ok" : status === 409 ? "refused" : "error";
  showMessage(kind, text, state ? `state:${state}` : "");
}

/** Show one message. `clears`: what ends it before the next one does: "reset" (a fault:
 * gone once the cell has no stop reason; it stayed on screen after the reset), "live" (a
 * STOP that could not reach the server: see stopNotDelivered), "stopped" (gone once the
 * cell is in ERROR). */
export function showMessage(kind, text, clears = "") {
  const box = $("message");
  hmi.shown += 1;
  box.hidden = false;
  box.dataset.kind = kind;
  box.dataset.clears = clears;
  box.textContent = `${clockTime(Date.now() / 1000)}  ${text}`;
}

/** Live again after a STOP that could not be sent: that stop was never made. Unless the
 * cell stopped anyway, say so with the state it is in, until it stops. */
function stopNotDelivered() {
  if ($("message").dataset.clears !== "live") return;
  const state = hmi.view?.state;
  if (state === "ERROR") {
    clearMessage("live");
    return;
  }
  const now = state ? state.replaceAll("_", " ") : "unknown";
  showMessage(
    "error",
    `a STOP pressed while the server was unreachable was not made; the cell is ${now}: ` +
      "press STOP again, or use the e-stop",
    "stopped",
  );
}

/** Hide the message if it is one that `condition` ends (any, without a condition). */
export function clearMessage(condition) {
  const box = $("message");
  if (condition && box.dataset.clears !== condition) return;
  box.hidden = true;
  box.textContent = "";
  box.dataset.clears = "";
}

// --- progress ---------------------------------------------------------------

export function startProgress(operation, runId) {
  hmi.progress = { operation, run_id: runId, waypoint: 0, total: 0, fraction: 0, ended: null };
}

export function updateProgress(update) {
  const progress = hmi.progress;
  if (!progress) return;
  if (update.run_id) progress.run_id = update.run_id;
  for (const key of ["waypoint", "total", "fraction", "workpiece_id", "step", "views"]) {
    if (update[key] !== undefined) progress[key] = update[key];
  }
}

export function renderProgress() {
  const progress = hmi.progress;
  const bar = $("progress");
  const fraction = progress ? Math.max(0, Math.min(1, progress.fraction || 0)) : 0;
  bar.setAttribute("aria-valuenow", String(Math.round(fraction * 100)));
  bar.dataset.waypoint = String(progress?.waypoint || 0);
  bar.dataset.total = String(progress?.total || 0);
  bar.dataset.ended = progress?.ended ? "true" : "false";
  $("progress-fill").style.width = `${(fraction * 100).toFixed(1)}%`;
  $("progress-label").textContent = progressLabel(progress, fraction);
  $("progress-workpiece").textContent = progress?.workpiece_id || "—";
  $("progress-run").textContent = progress?.run_id ? `run ${progress.run_id}` : "";
  $("progress-note").textContent = progress?.ended ? `last run ${progress.ended}` : "";
}

function progressLabel(progress, fraction) {
  if (!progress) return "no operation";
  const percent = `${Math.round(fraction * 100)} %`;
  if (progress.waypoint) return `waypoint ${progress.waypoint} of ${progress.total} · ${percent}`;
  if (progress.views !== undefined) return `view ${progress.views} of ${progress.total} · ${percent}`;
  if (progress.step) return `${progress.step} · ${percent}`;
  return "starting…";
}
