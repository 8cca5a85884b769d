/* The trajectory canvas: the planned path over the latest camera frame (or the
 * robot calibration's image), the executed part in its own colour, the robot's
 * waypoint. The geometry is in geometry.js; this module fetches and draws. */

import { api, blobUrl, getJson } from "./api.js";
import { $, clockTime } from "./dom.js";
import {
  boundingBox,
  canvasSize,
  containRect,
  fitToCanvas,
  tableToImage,
  viewWindow,
  windowToCanvas,
} from "./geometry.js";
import { hmi } from "./store.js";

const DONE_COLOUR = "#ff4fd8"; // the executed path: unlike anything on the camera frame

/** Which plan is shown: a run's plan replaces its "not planned yet" placeholder. */
function planKey(trajectory) {
  return trajectory ? `${trajectory.run_id}:${trajectory.planned}` : null;
}

export async function refreshTrajectory() {
  const previousPlan = planKey(hmi.trajectory);
  try {
    const response = await api("GET", "/trajectory");
    hmi.trajectory = response.ok ? await response.json() : null;
    const reached = hmi.trajectory?.waypoint;
    if (reached && hmi.progress && hmi.progress.run_id === hmi.trajectory.run_id) {
      hmi.progress.waypoint = Math.max(hmi.progress.waypoint || 0, reached);
    }
  } catch {
    /* keep the last one */
  }
  // A new plan: its run has just looked at the table (with contour matching).
  if (hmi.trajectory?.planned && planKey(hmi.trajectory) !== previousPlan) refreshFrame();
  renderTrajectoryInfo();
  drawTrajectory();
}

function renderTrajectoryInfo() {
  const path = hmi.trajectory?.planned_path || [];
  const planned = hmi.trajectory?.planned ? `${path.length} waypoints` : "planning";
  const plan = hmi.trajectory
    ? `run ${hmi.trajectory.run_id} · ${planned}`
    : "no trajectory planned yet";
  const info = hmi.frameInfo;
  let over = "";
  if (hmi.frame && info) over = ` · camera ${clockTime(info.time)} (${info.source.replace(/_/g, " ")})`;
  else if (hmi.calibrationImage) over = " · calibration image";
  $("trajectory-info").textContent = plan + over;
}

export async function refreshCalibration() {
  try {
    hmi.calibration = await getJson("/calibration");
    const url = hmi.calibration?.robot?.has_image ? await blobUrl("/calibration/image") : null;
    if (url) hmi.calibrationImage = await loadImage(url);
  } catch {
    /* the path is drawn without a background */
  }
  renderTrajectoryInfo();
  drawTrajectory();
}

let frameAsks = 0; // only the answer to the latest request is shown

/** The latest frame an operation captured (GET /camera/frame, 404 until one did). A 404
 * drops the frame shown: the server has none (it restarted), so the calibration image
 * stands in rather than a picture of a run the server no longer knows. */
export async function refreshFrame() {
  const ask = ++frameAsks;
  try {
    const response = await api("GET", "/camera/frame");
    if (ask !== frameAsks) return; // overtaken by a later request
    if (response.status === 404) {
      hmi.frame = null;
      hmi.frameInfo = null;
    } else if (response.ok) {
      const info = {
        time: Number(response.headers.get("X-Frame-Time")),
        source: response.headers.get("X-Frame-Source") || "",
        run: response.headers.get("X-Frame-Run-Id") || "",
      };
      const shown = hmi.frameInfo;
      if (shown && info.time === shown.time && info.run === shown.run) return; // the same one
      const image = await loadImage(URL.createObjectURL(await response.blob()));
      if (!image || ask !== frameAsks) return;
      hmi.frame = image;
      hmi.frameInfo = info;
    } else {
      return; // a passing failure: keep the last one
    }
  } catch {
    return; /* keep the last one */
  }
  renderTrajectoryInfo();
  drawTrajectory();
}

/** A new server process (another `boot`): its runs and frames are not the ones shown. */
export function forgetRuns() {
  hmi.trajectory = null;
  hmi.frame = null;
  hmi.frameInfo = null;
  renderTrajectoryInfo();
  drawTrajectory();
}

function loadImage(url) {
  return new Promise((resolve) => {
    const image = new Image();
    image.onload = () => {
      URL.revokeObjectURL(url);
      resolve(image);
    };
    image.onerror = () => resolve(null);
    image.src = url;
  });
}

// --- drawing ------------------------------------------------------------------

function fitCanvas(canvas) {
  const ratio = window.devicePixelRatio || 1;
  const size = canvasSize(canvas.parentElement.getBoundingClientRect(), ratio);
  if (canvas.width !== size.pixelWidth || canvas.height !== size.pixelHeight) {
    canvas.width = size.pixelWidth;
    canvas.height = size.pixelHeight;
  }
  const ctx = canvas.getContext("2d");
  ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
  return { ctx, width: size.width, height: size.height };
}

export function drawTrajectory() {
  const { ctx, width, height } = fitCanvas($("trajectory-canvas"));
  ctx.fillStyle = "#10151b";
  ctx.fillRect(0, 0, width, height);
  const path = hmi.trajectory?.planned_path || [];
  const project = projection(ctx, path, width, height);
  if (!path.length || !project) {
    return caption(ctx, width, height, "no trajectory planned since the server started");
  }
  const points = path.map((w) => project(w.pose));
  const reached = Math.min(currentWaypoint(), path.length);
  drawSegments(ctx, path, points, 0, path.length, false);
  drawSegments(ctx, path, points, 0, reached, true);
  points.forEach((p) => dot(ctx, p, 2.5, "rgba(230,238,245,0.8)"));
  if (reached > 0) dot(ctx, points[reached - 1], 8, "#ffffff", "#2f8cff");
}

function currentWaypoint() {
  const progress = hmi.progress;
  if (!progress || progress.run_id !== hmi.trajectory?.run_id) return 0;
  return progress.waypoint || 0;
}

/** mm → canvas: over the camera frame through the calibration, else by the path's own box.
 * The latest frame an operation captured, else the robot calibration's own image. */
function projection(ctx, path, width, height) {
  const toImage = tableToImage(hmi.calibration?.robot?.homography);
  const frame = hmi.frame || hmi.calibrationImage;
  const canvas = $("trajectory-canvas");
  canvas.dataset.background = "none";
  if (frame) canvas.dataset.background = hmi.frame ? "camera" : "calibration";
  if (frame && !path.length) {
    drawContained(ctx, frame, width, height);
    return null;
  }
  if (frame && !toImage) canvas.dataset.background = "none";
  if (frame && toImage) {
    const inImage = path.map((w) => toImage(w.pose));
    const { naturalWidth: imageW, naturalHeight: imageH } = frame;
    const box = viewWindow(boundingBox(inImage), width / height, imageW, imageH);
    ctx.drawImage(frame, box.x, box.y, box.w, box.h, 0, 0, width, height);
    const toCanvas = windowToCanvas(box, width, height);
    return (pose) => toCanvas(toImage(pose));
  }
  if (!path.length) return null;
  const toCanvas = fitToCanvas(boundingBox(path.map((w) => w.pose)), width, height);
  drawGrid(ctx, width, height);
  return toCanvas;
}

/** The whole frame, letterboxed, undistorted in shape. */
function drawContained(ctx, image, width, height) {
  const { x, y, w, h } = containRect(image.naturalWidth, image.naturalHeight, width, height);
  ctx.drawImage(image, x, y, w, h);
}

function drawSegments(ctx, path, points, from, to, done) {
  ctx.lineCap = "round";
  ctx.lineJoin = "round";
  for (let i = Math.max(1, from); i < to; i += 1) {
    const spray = path[i].spray;
    ctx.beginPath();
    ctx.moveTo(...points[i - 1]);
    ctx.lineTo(...points[i]);
    ctx.setLineDash(spray || done ? [] : [6, 6]);
    ctx.lineWidth = done ? 6 : spray ? 4 : 2;
    ctx.strokeStyle = done ? DONE_COLOUR : spray ? "rgba(86,180,255,0.95)" : "rgba(200,210,220,0.7)";
    ctx.stroke();
  }
  ctx.setLineDash([]);
}

function drawGrid(ctx, width, height) {
  ctx.strokeStyle = "rgba(255,255,255,0.05)";
  ctx.lineWidth = 1;
  for (let x = 0; x < width; x += 40) line(ctx, [x, 0], [x, height]);
  for (let y = 0; y < height; y += 40) line(ctx, [0, y], [width, y]);
}

function line(ctx, a, b) {
  ctx.beginPath();
  ctx.moveTo(...a);
  ctx.lineTo(...b);
  ctx.stroke();
}

function dot(ctx, [x, y], radius, fill, stroke) {
  ctx.beginPath();
  ctx.arc(x, y, radius, 0, 2 * Math.PI);
  ctx.fillStyle = fill;
  ctx.fill();
  if (stroke) {
    ctx.lineWidth = 3;
    ctx.strokeStyle = stroke;
    ctx.stroke();
  }
}

function caption(ctx, width, height, text) {
  ctx.fillStyle = "rgba(0,0,0,0.55)";
  ctx.fillRect(0, height / 2 - 22, width, 44);
  ctx.fillStyle = "#c9d3dd";
  ctx.font = "16px system-ui, sans-serif";
  ctx.textAlign = "center";
  ctx.textBaseline = "middle";
  ctx.fillText(text, width / 2, height / 2);
}
