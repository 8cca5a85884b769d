/* The Set-up page: the camera's live set-up view (WebSocket /camera/preview/ws) and its
 * focus and exposure figures, for a technician placing markers, focusing and lighting
 * the table before calibrating. The stream runs only while this page watches it.
 *
 * A WebSocket rather than an <img> on an MJPEG URL: an <img> cannot send the bearer
 * header. The page asks POST /ws-ticket for a one-shot ticket, as the dashboard does for
 * /ws. Each frame arrives as its figures (text) then its JPEG (binary).
 */

import { api, errorText, getJson, tryToken, whenUnauthorized } from "./api.js";
import { $, facts, number } from "./dom.js";
import { mountMarkerLayout } from "./markers.js";
import { TOKEN_KEY, hmi } from "./store.js";

const view = { socket: null, image: null, figures: null, frames: 0 };

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

let unmountMarkers = null;

function start(token) {
  hmi.token = token;
  $("login").hidden = true;
  $("app").hidden = false;
  if (!unmountMarkers) unmountMarkers = mountMarkerLayout($("marker-layout"));
  openView();
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
    status(`Not started: ${preview.reason}`);
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
    status(closed.reason ? `Stopped: ${closed.reason}` : "Stopped.");
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
$("view-toggle").addEventListener("click", () => (view.socket ? closeView() : openView()));
whenUnauthorized((message) => {
  sessionStorage.removeItem(TOKEN_KEY);
  closeView();
  if (unmountMarkers) unmountMarkers();
  unmountMarkers = null;
  showLogin(message);
});
window.addEventListener("pagehide", closeView);

const saved = sessionStorage.getItem(TOKEN_KEY);
if (saved) start(saved);
else showLogin("");

