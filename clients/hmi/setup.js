/* The Set-up page: the camera's live set-up view (WebSocket /camera/preview/ws) and its
 * focus and exposure figures, for a technician placing markers, focusing and lighting
 * the table before calibrating. The stream runs only while this page watches it.
 *
 * Safe to work from: STOP and the cell's state are in the header at every size (the
 * state read every half second from GET /state); Home, jog and teach are live only when
 * the server would accept them (GET /state's `may`: the state and the role); the view,
 * which the server ends when the cell leaves IDLE, opens again by itself once the cell
 * is back in IDLE, unless the technician stopped it.
 *
 * A WebSocket rather than an <img> on an MJPEG URL: an <img> cannot send the bearer
 * header. The page asks POST /ws-ticket for a one-shot ticket, as the dashboard does for
 * /ws. Each frame arrives as its figures (text) then its JPEG (binary).
 */

import { AuthError, api, errorText, getJson, tryToken, whenUnauthorized } from "./api.js";
import { $, facts, number } from "./dom.js";
import { mountMarkerLayout } from "./markers.js";
import { TOKEN_KEY, hmi } from "./store.js";

const STATE_POLL_MS = 500;
// stopped: the technician stopped the view (it does not reopen by itself).
const view = { socket: null, image: null, figures: null, frames: 0, stopped: false };
const cell = { state: null, may: new Set(), timer: null, setup: false };

function showLogin(message) {
  $("app").hidden = true;
  $("login").hidden = false;
  $("login-error").hidden = !message;
  $("login-error").textContent = message || "";
}

function status(text) {
  $("setup-status").textContent = text;
}

async function signIn(event) {
  event.preventDefault();
  const token = $("token-input").value.trim();
  if (!token) return;
  const result = await tryToken(token);
  if (!result.ok) {
    showLogin(result.message);
    return;
  }
  sessionStorage.setItem(TOKEN_KEY, token);
  $("token-input").value = "";
  start(token);
}

let markers = null;

async function start(token) {
  hmi.token = token;
  $("login").hidden = true;
  $("app").hidden = false;
  try {
    cell.setup = Boolean((await getJson("/me")).pages.setup);
  } catch (error) {
    if (error instanceof AuthError) return;
  }
  if (!markers && cell.setup) markers = mountMarkerLayout($("marker-layout"), $("setup-jog"), allows);
  await pollState();
  if (!cell.timer) cell.timer = setInterval(pollState, STATE_POLL_MS);
  openView();
}

/** Whether the server would accept `command` now: the state allows it and the role may. */
function allows(command) {
  if (command === "teach") return cell.setup && cell.state === "IDLE";
  return cell.may.has(command);
}

/** The cell's state in the header; Home and the jog panel follow it; back in IDLE, the
 * view opens again unless the technician stopped it. */
async function pollState() {
  let state;
  try {
    state = await getJson("/state");
  } catch (error) {
    if (!(error instanceof AuthError)) showState(null, "no answer from the server");
    return;
  }
  const before = cell.state;
  cell.state = state.state;
  cell.may = new Set(state.may || []);
  showState(state.state, state.stop_reason ? state.stop_reason.message : "");
  $("setup-home").disabled = !allows("home");
  if (markers) markers.renderControls();
  if (state.state === "IDLE" && before !== "IDLE" && before !== null) {
    if (!view.socket && !view.stopped) openView();
  }
  clearSetupMessage();
  if (state.state === "ERROR" && state.stop_reason) sayStopped(state.stop_reason.message);
}

/** Stopped: why, and what to do next in words, on this page too (this page has no
 * Reset: the dashboard's state card is where a stop is reset). */
function sayStopped(reason) {
  const next = cell.may.has("reset")
    ? "Reset it on the Dashboard once the cell is clear."
    : "Call maintenance to reset: needs the maintenance role.";
  const text = `Stopped: ${reason}. ${next}`;
  if ($("setup-message").textContent !== text || $("setup-message").hidden) say("error", text, "ERROR");
}

function showState(state, detail) {
  const box = $("setup-state");
  box.dataset.state = state || "UNKNOWN";
  box.textContent = state ? state.replaceAll("_", " ") : "not live";
  box.title = detail || "";
}

/** Show a message about the cell in `state` (the answer's, else the one shown now). */
function say(kind, text, state) {
  const box = $("setup-message");
  box.hidden = false;
  box.dataset.kind = kind;
  box.dataset.state = state || cell.state || "";
  box.textContent = text;
}

/** A message describes the state it was said in: gone once the cell has left it. */
function clearSetupMessage() {
  const box = $("setup-message");
  if (box.dataset.state && box.dataset.state !== cell.state) box.hidden = true;
}

/** A command's answer in words, with the state it left the cell in. */
async function answer(response) {
  const text = await errorText(response);
  let state = null;
  try {
    state = (await response.clone().json()).state || null;
  } catch {
    state = null;
  }
  say(response.ok ? "ok" : response.status === 409 ? "refused" : "error", text, state);
}

async function command(path, body) {
  try {
    await answer(await api("POST", path, body));
  } catch (error) {
    if (!(error instanceof AuthError)) say("error", error.message);
  }
  await pollState();
}

/** Ask whether the view may open; open it with a ticket if so, else say why. */
async function openView() {
  if (view.socket) return;
  let preview;
  try {
    preview = await getJson("/camera/preview");
  } catch (error) {
    status(`The set-up view is not available: ${error.message}`);
    return;
  }
  if (!preview.allowed) {
    const again = cell.state && cell.state !== "IDLE" ? "; it opens again when the cell is IDLE" : "";
    status(`Not started: ${preview.reason}${again}`);
    return;
  }
  const answer = await api("POST", "/ws-ticket");
  if (!answer.ok) {
    status(`Not started: ${await errorText(answer)}`);
    return;
  }
  const { ticket } = await answer.json();
  const scheme = location.protocol === "https:" ? "wss" : "ws";
  const socket = new WebSocket(`${scheme}://${location.host}/camera/preview/ws?ticket=${ticket}`);
  socket.binaryType = "blob";
  view.socket = socket;
  status(`Starting (at most ${preview.fps} frames a second)…`);
  renderToggle();
  socket.onmessage = (message) => {
    if (typeof message.data === "string") {
      view.figures = JSON.parse(message.data);
      renderFigures(view.figures);
    } else {
      showFrame(message.data);
    }
  };
  socket.onclose = (closed) => {
    if (view.socket === socket) view.socket = null;
    renderToggle();
    const again = view.stopped ? "" : " It opens again when the cell is IDLE.";
    status(closed.reason ? `Stopped: ${closed.reason}.${again}` : `Stopped.${again}`);
  };
}

function closeView() {
  const socket = view.socket;
  view.socket = null;
  if (socket) socket.close(1000, "the technician stopped the view");
  renderToggle();
}

function showFrame(blob) {
  const image = $("setup-image");
  const url = URL.createObjectURL(blob);
  const previous = view.image;
  view.image = url;
  image.onload = () => previous && URL.revokeObjectURL(previous);
  image.src = url;
  image.hidden = false;
  view.frames += 1;
  image.dataset.frames = String(view.frames);
  status(`Live: frame ${view.figures ? view.figures.seq : "?"}`);
}

function renderFigures(figures) {
  const markers = `${figures.markers_found} of ${figures.markers_expected}`;
  const missing = figures.missing.length ? `missing ${figures.missing.join(", ")}` : "all found";
  const clipped = `${number(figures.over_exposed_pct, 1)} % white, ${number(figures.under_exposed_pct, 1)} % black`;
  const list = facts([
    ["Markers found", markers, figures.missing.length ? "tone-hold" : "tone-ok"],
    ["Markers", missing],
    ["Sharpness", number(figures.sharpness, 0)],
    ["Brightness", `${number(figures.brightness, 0)} of 255`],
    ["Clipped", clipped],
    ["Workspace", figures.workspace_drawn ? "outlined through the robot calibration" : figures.workspace_note],
    ["Frame", figures.undistorted ? "undistorted (camera calibration)" : "as the camera delivers it"],
  ]);
  list.id = "figures-list";
  list.dataset.markersFound = String(figures.markers_found);
  $("setup-figures").replaceChildren(list);
}

function renderToggle() {
  const button = $("view-toggle");
  button.textContent = view.socket ? "Stop view" : "Start view";
}

$("login-form").addEventListener("submit", signIn);
$("view-toggle").addEventListener("click", () => {
  view.stopped = Boolean(view.socket); // the technician's choice: kept until Start view
  if (view.socket) closeView();
  else openView();
});
$("setup-home").addEventListener("click", () => command("/home"));
$("estop").addEventListener("click", async () => {
  try {
    await answer(await api("POST", "/estop", { reason: "STOP pressed on the Set-up page" }));
  } catch (error) {
    if (!(error instanceof AuthError)) {
      say("error", `STOP could not reach the server (${error.message}): use the e-stop`);
    }
  }
  await pollState();
});
whenUnauthorized((message) => {
  sessionStorage.removeItem(TOKEN_KEY);
  closeView();
  clearInterval(cell.timer);
  cell.timer = null;
  if (markers) markers.unmount();
  markers = null;
  showLogin(message);
});
window.addEventListener("pagehide", closeView);

const saved = sessionStorage.getItem(TOKEN_KEY);
if (saved) start(saved);
else showLogin("");

