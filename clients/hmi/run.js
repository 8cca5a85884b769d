/* The run page: one run's flight recording replayed (GET /runs/{run_id}/recording).
 *
 * The path is drawn over the run's frame: the inspection's annotated image when it is
 * kept, else the camera's latest frame, mapped from the robot's mm to image pixels by
 * the robot calibration's homography (geometry.js: tableToImage), magenta where glue
 * flowed. Flow, pressure and speed are charted against time (inline SVG, the valve's
 * open spans shaded); the slider and Play move one cursor through both. The token is
 * the dashboard's session token (sessionStorage): this page signs nobody in. */

import { api, blobUrl, errorText, getJson } from "./api.js";
import { $, clockTime, element, facts, number } from "./dom.js";
import { containRect, tableToImage } from "./geometry.js";
import { openSpans, pathSegments, polylines, sampleAt, SERIES } from "./run_view.js";
import { hmi, TOKEN_KEY } from "./store.js";

const SVG = "http://www.w3.org/2000/svg";
const CHART_W = 600, CHART_H = 90;
const PLAY_S = 10; // a replay takes this long, whatever the run's length
const OPEN_COLOUR = "#ff4fd8", CLOSED_COLOUR = "rgba(255,255,255,0.55)";

const page = { recording: null, samples: [], image: null, toImage: null, at: 1, playing: null };

function say(text) {
  const box = $("run-message");
  box.hidden = !text;
  box.textContent = text || "";
}

function svg(tag, attributes) {
  const node = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attributes)) node.setAttribute(k, String(v));
  return node;
}

function loadImage(url) {
  return new Promise((resolve) => {
    const image = new Image();
    image.onload = () => resolve(image);
    image.onerror = () => resolve(null);
    image.src = url;
  });
}

function span() {
  const s = page.samples;
  return s.length ? [s[0].time, Math.max(s[s.length - 1].time, s[0].time + 1e-3)] : [0, 1];
}

function drawCharts() {
  const [t0, t1] = span();
  const charts = SERIES.map(([label, key, unit, colour]) => {
    const chart = svg("svg", { viewBox: `0 0 ${CHART_W} ${CHART_H}`, class: "run-chart", "data-series": key });
    for (const [a, b] of openSpans(page.samples)) {
      const x = ((a - t0) / (t1 - t0)) * CHART_W;
      chart.append(svg("rect", { x, y: 0, width: ((b - a) / (t1 - t0)) * CHART_W, height: CHART_H, fill: "rgba(255,79,216,0.12)" }));
    }
    for (const points of polylines(page.samples, key, t0, t1, CHART_W, CHART_H)) {
      chart.append(svg("polyline", { points, fill: "none", stroke: colour, "stroke-width": 2 }));
    }
    chart.append(svg("line", { class: "run-cursor", x1: 0, x2: 0, y1: 0, y2: CHART_H, stroke: "#fff" }));
    const values = page.samples.map((s) => s[key]).filter((v) => typeof v === "number");
    const top = values.length ? `${number(Math.max(...values), 1)} ${unit}` : "not recorded";
    const caption = element("div", "muted small", `${label} (${unit}) · max ${top}`);
    const box = element("div", "run-series");
    box.append(caption, chart);
    return box;
  });
  $("run-charts").replaceChildren(...charts);
}

function drawPath() {
  const canvas = $("run-canvas");
  const box = canvas.getBoundingClientRect();
  canvas.width = Math.max(320, Math.round(box.width));
  canvas.height = Math.round(canvas.width * 0.75);
  const ctx = canvas.getContext("2d");
  ctx.fillStyle = "#111";
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  const image = page.image;
  let toCanvas;
  if (image && page.toImage) {
    const r = containRect(image.width, image.height, canvas.width, canvas.height);
    ctx.drawImage(image, r.x, r.y, r.w, r.h);
    const s = r.w / image.width;
    toCanvas = (p) => {
      const [u, v] = page.toImage(p);
      return [r.x + u * s, r.y + v * s];
    };
  } else {
    toCanvas = fitMillimetres(canvas);
  }
  const upTo = page.samples.slice(0, sampleAt(page.samples, currentTime()) + 1);
  for (const segment of pathSegments(upTo)) {
    ctx.strokeStyle = segment.open ? OPEN_COLOUR : CLOSED_COLOUR;
    ctx.lineWidth = segment.open ? 3 : 1.5;
    ctx.beginPath();
    segment.points.map(toCanvas).forEach(([x, y], k) => (k ? ctx.lineTo(x, y) : ctx.moveTo(x, y)));
    ctx.stroke();
  }
  const last = [...upTo].reverse().find((s) => typeof s.x_mm === "number");
  if (last) {
    const [x, y] = toCanvas([last.x_mm, last.y_mm]);
    ctx.fillStyle = "#fff";
    ctx.beginPath();
    ctx.arc(x, y, 5, 0, 2 * Math.PI);
    ctx.fill();
  }
}

/** Without a frame and a calibration: the path fitted to the canvas in mm (y up). */
function fitMillimetres(canvas) {
  const points = page.samples.filter((s) => typeof s.x_mm === "number");
  if (!points.length) return () => [0, 0];
  const xs = points.map((s) => s.x_mm), ys = points.map((s) => s.y_mm);
  const x0 = Math.min(...xs), y0 = Math.min(...ys);
  const w = Math.max(Math.max(...xs) - x0, 1), h = Math.max(Math.max(...ys) - y0, 1);
  const scale = Math.min((canvas.width - 40) / w, (canvas.height - 40) / h);
  return ([x, y]) => [20 + (x - x0) * scale, canvas.height - 20 - (y - y0) * scale];
}

function currentTime() {
  const [t0, t1] = span();
  return t0 + page.at * (t1 - t0);
}

function showCursor() {
  const [t0, t1] = span();
  const x = ((currentTime() - t0) / (t1 - t0)) * CHART_W;
  for (const line of document.querySelectorAll(".run-cursor")) {
    line.setAttribute("x1", x);
    line.setAttribute("x2", x);
  }
  const sample = page.samples[sampleAt(page.samples, currentTime())];
  $("run-clock").textContent = sample ? clockTime(sample.time) : "";
  const show = (v, digits, unit) => (typeof v === "number" ? `${number(v, digits)} ${unit}` : "—");
  $("run-sample").replaceChildren(
    ...(sample
      ? [facts([
        ["valve", sample.valve_open ? "open" : "closed"],
        ["flow", show(sample.flow_ml_min, 1, "ml/min")],
        ["pressure", show(sample.pressure_psi, 1, "psi")],
        ["speed", show(sample.speed_mm_s, 0, "mm/s")],
      ])]
      : []),
  );
  drawPath();
}

function seek(at) {
  page.at = Math.min(1, Math.max(0, at));
  $("run-time").value = String(Math.round(page.at * 1000));
  showCursor();
}

function play() {
  if (page.playing) {
    cancelAnimationFrame(page.playing);
    page.playing = null;
    $("run-play").textContent = "Play";
    return;
  }
  const began = performance.now() - (page.at >= 1 ? 0 : page.at * PLAY_S * 1000);
  $("run-play").textContent = "Pause";
  const step = (now) => {
    seek((now - began) / (PLAY_S * 1000));
    if (page.at < 1) page.playing = requestAnimationFrame(step);
    else play();
  };
  page.playing = requestAnimationFrame(step);
}

function renderFacts(recording) {
  const run = recording.run;
  const inspection = recording.inspection;
  const verdict = $("run-verdict");
  verdict.textContent = inspection ? inspection.verdict : `not inspected (run ${run.outcome || "running"})`;
  verdict.dataset.kind = { good: "ok", defective: "fault" }[inspection?.verdict] || "";
  const seconds = run.ended_at ? run.ended_at - run.started_at : null;
  $("run-summary").replaceChildren(facts([
    ["operation", run.kind],
    ["outcome", run.outcome || "running"],
    ["started", clockTime(run.started_at)],
    ["took", seconds === null ? "—" : `${number(seconds, 1)} s`],
    ["samples", `${recording.samples.length} every ${number(recording.sample_period_s, 2)} s`],
  ]));
  $("run-reasons").replaceChildren(...(inspection?.reasons || []).map((r) => element("li", "", String(r))));
  const stop = recording.stop_reason;
  $("run-stop").textContent = stop
    ? `stopped by ${stop.code} (${stop.component}): ${stop.message}`
    : run.error ? `stopped: ${run.error}` : "no fault stopped it";
  if (!recording.recorded) say("The flight recorder is off (run_recording): no samples were kept.");
  else if (!recording.samples.length) say("No samples were recorded for this run.");
}

async function frameFor(recording) {
  const id = encodeURIComponent(recording.run_id);
  if (recording.inspection?.has_image) {
    const url = await blobUrl(`/runs/${id}/inspection.jpg`);
    if (url) return [await loadImage(url), "inspection image"];
  }
  const url = await blobUrl("/camera/frame").catch(() => null);
  return url ? [await loadImage(url), "latest camera frame"] : [null, "no frame"];
}

async function start() {
  const runId = new URLSearchParams(location.search).get("run");
  hmi.token = sessionStorage.getItem(TOKEN_KEY);
  if (!hmi.token) return say("Sign in on the dashboard first, then open the run from its Last part card.");
  if (!runId) return say("No run named: open a run from the dashboard's Last part card.");
  $("run-title").textContent = `run ${runId}`;
  const response = await api("GET", `/runs/${encodeURIComponent(runId)}/recording`);
  if (!response.ok) return say(await errorText(response));
  const recording = await response.json();
  page.recording = recording;
  page.samples = recording.samples;
  const calibration = await getJson("/calibration").catch(() => null);
  page.toImage = tableToImage(calibration?.robot?.homography);
  const [image, source] = await frameFor(recording);
  page.image = image;
  $("run-frame").textContent = page.toImage && image ? source : "robot frame (mm), no calibrated image";
  $("run-csv").onclick = async (event) => {
    event.preventDefault();
    const url = await blobUrl(`/runs/${encodeURIComponent(runId)}/recording?format=csv`);
    if (url) Object.assign(document.createElement("a"), { href: url, download: `run-${runId}.csv` }).click();
  };
  renderFacts(recording);
  drawCharts();
  seek(1);
  $("run-time").addEventListener("input", (e) => seek(Number(e.target.value) / 1000));
  $("run-play").addEventListener("click", play);
  window.addEventListener("resize", drawPath);
  document.body.dataset.ready = "true";
}

start().catch((error) => say(String(error.message || error)));
