/* Operator dashboard of the glue cell: plain JavaScript modules, no framework, no
 * build step. This is the entry (index.html loads it as a module; the name stays
 * app.js so that the page's address for its script does not change):
 * sign-in, the session, the command buttons, and the page's test hook.
 *
 *   store.js       what the page knows (the last state, the link, the run)
 *   api.js         fetch with the token; 401 signs out
 *   live.js        the WebSocket: ticket, snapshot, messages, reconnect
 *   render.js      state, fault, command buttons, messages, progress
 *   panels.js      devices, KPIs, history, the workpiece library
 *   settings_card.js  the settings changed at once, for a role that may read them
 *   trajectory.js  the trajectory canvas (fetching and drawing)
 *   geometry.js    its pure geometry: mm ↔ image ↔ canvas (tested with node)
 *   dom.js         DOM and text helpers
 *
 * What the server says is the only truth: the state, the commands it allows
 * (available_commands), the messages it answers. The page keeps a copy of the
 * last state it received and shows it as live only while the WebSocket is up.
 */

import { AuthError, api, errorText, tryToken, whenUnauthorized } from "./api.js";
import { $ } from "./dom.js";
import { connect, dropConnection, dropSocket, watchdog } from "./live.js";
import { initOrders } from "./orders.js";
import { refreshLibrary, refreshPanels } from "./panels.js";
import {
  applyState, clearMessage, renderCommands, setLive, showAnswer, showMessage, tick,
} from "./render.js";
import { forgetMe, refreshMe } from "./role.js";
import { initSettings, refreshSettings } from "./settings_card.js";
import { hmi, REFRESH_MS, TOKEN_KEY } from "./store.js";
import { drawTrajectory, refreshCalibration, refreshFrame, refreshTrajectory } from "./trajectory.js";
import { refreshTrends, TRENDS_MS } from "./trends.js";

// --- login ------------------------------------------------------------------

async function onLogin(event) {
  event.preventDefault();
  const token = $("token-input").value.trim();
  if (!token) return;
  $("login-button").disabled = true;
  try {
    const result = await tryToken(token);
    if (!result.ok) return showLoginError(result.message);
    sessionStorage.setItem(TOKEN_KEY, token);
    $("token-input").value = "";
    startSession(token, result.view);
  } catch (error) {
    showLoginError(`the server cannot be reached: ${error.message}`);
  } finally {
    $("login-button").disabled = false;
  }
}

function showLoginError(message) {
  $("login-error").textContent = message;
  $("login-error").hidden = false;
}

function showLogin(message) {
  $("app").hidden = true;
  $("login").hidden = false;
  $("login-error").hidden = !message;
  $("login-error").textContent = message || "";
  $("token-input").focus();
}

function signOut(message) {
  sessionStorage.removeItem(TOKEN_KEY);
  stopSession();
  clearMessage(); // the next person does not see the last one's answers
  showLogin(message);
}

function startSession(token, view) {
  hmi.token = token;
  $("login").hidden = true;
  $("app").hidden = false;
  if (view) applyState(view);
  setLive(false, "connecting…");
  refreshMe().then(renderCommands).catch(() => {}); // a 401 signs out by itself
  connect();
  refreshPanels();
  refreshTrajectory();
  refreshCalibration();
  refreshFrame();
  refreshLibrary();
  refreshTrends();
  refreshSettings();
  hmi.timers.push(setInterval(refreshPanels, REFRESH_MS));
  hmi.timers.push(setInterval(refreshTrends, TRENDS_MS));
  hmi.timers.push(setInterval(tick, 250));
  hmi.timers.push(setInterval(watchdog, 1000));
}

function stopSession() {
  hmi.timers.forEach(clearInterval);
  hmi.timers = [];
  clearTimeout(hmi.reconnectTimer);
  hmi.reconnectTimer = null;
  dropSocket(null);
  hmi.token = null;
  forgetMe();
  document.querySelector(".card-settings").hidden = true; // the next person's role decides
}

// --- commands ---------------------------------------------------------------

async function sendCommand(name, body) {
  if (name === "create-workpiece" && body === undefined) return askWorkpiece();
  hmi.pending.add(name);
  renderCommands();
  const shown = hmi.shown;
  try {
    const response = await api("POST", `/${name}`, body);
    // An acceptance says less than what was shown while it was on its way (its run's end,
    // come first over the socket): it does not replace that.
    if (response.status === 202 && hmi.shown !== shown) return;
    showAnswer(response.status, await errorText(response), await stateOf(response));
  } catch (error) {
    if (!(error instanceof AuthError)) showMessage("error", `${name}: ${error.message}`);
  } finally {
    hmi.pending.delete(name);
    renderCommands();
  }
}

// --- create workpiece: named, and never a silent copy --------------------------

/** Ask the new part's name, then capture it only if it matches no stored part
 * (`if_new`); `workpieceCreated` asks before a copy is stored. */
function askWorkpiece() {
  const name = (window.prompt("Name of the new workpiece:") || "").trim();
  if (!name) return;
  hmi.creating = { name };
  sendCommand("create-workpiece", { name, if_new: true });
}

/** The capture this page asked for ended (`result`: the run's). If the part matched a
 * stored one, nothing was stored: say which, and store a copy only if the person says so. */
function workpieceCreated(result) {
  const asked = hmi.creating;
  hmi.creating = null;
  if (!asked || !result) return;
  if (result.stored !== false) {
    showMessage("ok", `workpiece ${result.name} stored as ${result.workpiece_id}`, "state:IDLE");
    return;
  }
  const similar = result.similar;
  const question = `The part on the table matches "${similar.name}" (${similar.workpiece_id}), ` +
    `its outline within ${similar.fit_error_mm} mm. Store it anyway as "${asked.name}"?`;
  if (window.confirm(question)) {
    hmi.creating = asked; // its end says where the copy was stored
    sendCommand("create-workpiece", { name: asked.name });
  }
  else showMessage("info", `not stored: the part is ${similar.name} (${similar.workpiece_id})`, "state:IDLE");
}

/** The state a command's answer says it left the cell in, if it says. */
async function stateOf(response) {
  try {
    const body = await response.clone().json();
    return typeof body.state === "string" ? body.state : null;
  } catch {
    return null;
  }
}

async function emergencyStop() {
  try {
    const response = await api("POST", "/estop", { reason: "STOP pressed on the HMI" });
    showAnswer(response.status, await errorText(response), await stateOf(response));
  } catch (error) {
    if (!(error instanceof AuthError)) {
      showMessage(
        "error", `STOP could not reach the server (${error.message}): use the e-stop`, "live",
      );
    }
  }
}

// --- start ------------------------------------------------------------------

function init() {
  whenUnauthorized(signOut);
  $("login-form").addEventListener("submit", onLogin);
  $("logout").addEventListener("click", () => signOut(""));
  $("estop").addEventListener("click", emergencyStop);
  for (const button of document.querySelectorAll("[data-command]")) {
    button.addEventListener("click", () => sendCommand(button.dataset.command));
  }
  initOrders();
  hmi.onWorkpieceCreated = workpieceCreated;
  initSettings();
  window.addEventListener("resize", drawTrajectory);
  const token = sessionStorage.getItem(TOKEN_KEY);
  if (token) startSession(token, null);
  else showLogin("");
}

window.hmi = {
  dropConnection,
  status: () => ({
    live: hmi.live,
    state: hmi.view?.state ?? null,
    attempts: hmi.attempts,
    ...hmi.counters,
  }),
};

init();
