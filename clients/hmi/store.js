/* What the page knows, shared by its modules: the last state the server sent,
 * the link, the progress of the run, the trajectory and its background. A copy
 * of the server's truth, shown as live only while the WebSocket is up.
 */

export const TOKEN_KEY = "gluecell.hmi.token";
export const REFRESH_MS = 3000;            // KPIs, history; health only while not live
// What the page asks /ws for: every record, and the live `device` samples.
export const LIVE_TYPES = ["state_changed", "progress", "error", "alert", "device"];
export const RECONNECT_FIRST_MS = 1000;    // then doubled up to RECONNECT_MAX_MS, with jitter
export const RECONNECT_MAX_MS = 10000;
export const WATCHDOG_PING_MS = 10000;     // ask the server for a pong after this much silence
export const WATCHDOG_DEAD_MS = 20000;     // and give the socket up after this much
export const HISTORY_ROWS = 20;

export const STATE_TONE = {
  IDLE: "ok",
  EXECUTING_TRAJECTORY: "busy",
  CALIBRATING_ROBOT: "busy",
  CALIBRATING_CAMERA: "busy",
  CREATING_WORKPIECE: "busy",
  PAUSED: "hold",
  ERROR: "fault",
  INITIALIZING: "init",
};
export const ENDINGS = {
  OPERATION_COMPLETED: "completed",
  CANCEL_REQUESTED: "cancelled",
  OPERATION_FAILED: "failed",
  EMERGENCY_STOP: "stopped",
  ERROR_OCCURRED: "stopped by a fault",
};

export const hmi = {
  token: null,
  me: null,              // GET /me: name, role, the commands the role may send (role.js)
  view: null,            // the last StateView received
  health: null,          // the last GET /health, kept current by `device` messages
  enteredAtMs: 0,        // performance.now() when that state was entered
  live: false,
  ws: null,
  lastSeq: null,
  boot: null,            // the server process the snapshot came from (a restart changes it)
  lastMessageMs: 0,
  attempts: 0,
  reconnectTimer: null,
  progress: null,        // {run_id, operation, waypoint, total, fraction, workpiece_id, ended}
  trajectory: null,
  calibration: null,
  frame: null,           // the latest camera frame an operation captured (an Image)
  frameInfo: null,       // {time, source, run} of that frame (X-Frame-* headers)
  calibrationImage: null, // the annotated frame of the last robot calibration: the fallback
  thumbnails: [],        // blob URLs to release
  partImage: null,       // blob URL of the last part's inspection image, to release
  pending: new Set(),    // commands whose request is in flight
  shown: 0,              // messages shown so far (render.js: showMessage)
  renderHooks: [],       // drawn again with the command buttons (orders.js: its buttons)
  creating: null,        // the workpiece this page asked to capture: {name}
  onWorkpieceCreated: () => {}, // app.js: what the capture this page asked for found
  counters: { connects: 0, disconnects: 0, messages: 0, gaps: 0 },
  timers: [],
};

export function isOperational(state) {
  return STATE_TONE[state] === "busy" || state === "PAUSED";
}
