/* The Trends card: each part figure's control chart from GET /quality/trends, drawn as a
 * small SVG (the centre line, the band between the limits, a dot per part, a defective
 * part in red), with the drift the latest part shows written under it. The geometry and
 * the caption are pure (tests/unit/hmi/trends.test.mjs); `refreshTrends` draws them. */

import { getJson } from "./api.js";
import { $, element } from "./dom.js";

const SVG = "http://www.w3.org/2000/svg";
export const TRENDS_MS = 10000; // a chart gains a point per part: every 10 s is enough
export const CHART_W = 240;
export const CHART_H = 56;
const PAD = 4;

/** Where each part, the centre line and the limits sit in a width × height box. The
 * vertical range holds every point and both limits, so a drift is seen leaving the band. */
export function chartGeometry(chart, width = CHART_W, height = CHART_H) {
  const values = chart.points.map((p) => p.value);
  const marks = [chart.lower, chart.upper, chart.centre].filter((v) => typeof v === "number");
  const all = [...values, ...marks];
  if (!all.length) return { points: [], centre: null, lower: null, upper: null };
  let low = Math.min(...all), high = Math.max(...all);
  if (high - low < 1e-9) { low -= 1; high += 1; }
  const y = (v) => PAD + (height - 2 * PAD) * (1 - (v - low) / (high - low));
  const step = values.length > 1 ? (width - 2 * PAD) / (values.length - 1) : 0;
  return {
    points: chart.points.map((p, i) => ({
      x: values.length > 1 ? PAD + i * step : width / 2, y: y(p.value), good: p.good,
    })),
    centre: typeof chart.centre === "number" ? y(chart.centre) : null,
    lower: typeof chart.lower === "number" ? y(chart.lower) : null,
    upper: typeof chart.upper === "number" ? y(chart.upper) : null,
  };
}

function figure(value) {
  return typeof value === "number" ? value.toPrecision(3) : "—";
}

/** The line under a chart: the drift and which way, else the latest value and the limits. */
export function trendCaption(chart) {
  const latest = chart.points.length ? chart.points[chart.points.length - 1].value : null;
  if (chart.drift) return { text: `drifting ${chart.drift.direction}: ${chart.drift.rule}`, drift: true };
  if (chart.centre === null) {
    return { text: `${figure(latest)} ${chart.unit} · limits after ${chart.points.length ? "more" : "the first"} good parts`, drift: false };
  }
  return {
    text: `${figure(latest)} ${chart.unit} · limits ${figure(chart.lower)} to ${figure(chart.upper)}`,
    drift: false,
  };
}

function svgNode(tag, attributes) {
  const node = document.createElementNS(SVG, tag);
  for (const [name, value] of Object.entries(attributes)) node.setAttribute(name, String(value));
  return node;
}

function drawChart(chart) {
  const box = element("div", "trend");
  box.dataset.figure = chart.figure;
  box.dataset.drift = chart.drift ? chart.drift.direction : "";
  box.append(element("div", "trend-label", chart.label));
  const svg = svgNode("svg", {
    viewBox: `0 0 ${CHART_W} ${CHART_H}`, class: "trend-chart", role: "img",
    "aria-label": `${chart.label} control chart`,
  });
  const shape = chartGeometry(chart);
  if (shape.upper !== null && shape.lower !== null) {
    svg.append(svgNode("rect", {
      x: 0, y: shape.upper, width: CHART_W, height: Math.max(0, shape.lower - shape.upper),
      class: "trend-band",
    }));
  }
  if (shape.centre !== null) {
    svg.append(svgNode("line", { x1: 0, x2: CHART_W, y1: shape.centre, y2: shape.centre, class: "trend-centre" }));
  }
  if (shape.points.length > 1) {
    svg.append(svgNode("polyline", {
      points: shape.points.map((p) => `${p.x.toFixed(1)},${p.y.toFixed(1)}`).join(" "),
      class: "trend-line",
    }));
  }
  for (const p of shape.points) {
    svg.append(svgNode("circle", { cx: p.x.toFixed(1), cy: p.y.toFixed(1), r: 2, class: p.good ? "trend-dot" : "trend-dot bad" }));
  }
  const caption = trendCaption(chart);
  box.append(svg, element("div", caption.drift ? "trend-caption drift" : "trend-caption", caption.text));
  return box;
}

/** Fetch the charts and draw them; the card says how many parts they hold. */
export async function refreshTrends() {
  try {
    const trends = await getJson("/quality/trends");
    $("trends-count").textContent = `${trends.parts} parts`;
    $("trends").replaceChildren(...trends.charts.map(drawChart));
  } catch {
    /* a 401 signs out by itself; anything else: the charts stay as they were */
  }
}
