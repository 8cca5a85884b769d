/* The run page's pure helpers (no DOM): a recording's series, the chart's scales and
 * polylines, the sample shown at a replay time, the valve-open spans. Tested with
 * node --test (tests/unit/hmi/run_view.test.mjs). */

/** The chart series of a recording: [label, key, unit, colour]. */
export const SERIES = [
  ["flow", "flow_ml_min", "ml/min", "#4fc3f7"],
  ["pressure", "pressure_psi", "psi", "#ffb74d"],
  ["speed", "speed_mm_s", "mm/s", "#ff4fd8"],
];

/** The [lo, hi] of the numbers among `values` (nulls left out), widened when flat;
 * null when there is none. */
export function extent(values) {
  const numbers = values.filter((v) => typeof v === "number" && Number.isFinite(v));
  if (!numbers.length) return null;
  let lo = Math.min(...numbers), hi = Math.max(...numbers);
  if (hi - lo < 1e-9) [lo, hi] = [lo - 1, hi + 1];
  return [lo, hi];
}

/** The SVG `points` of one series over [t0, t1] in a w × h box (y up); a missing value
 * breaks the line, so the result is a list of polylines. */
export function polylines(samples, key, t0, t1, w, h) {
  const range = extent(samples.map((s) => s[key]));
  if (!range || t1 <= t0) return [];
  const [lo, hi] = range;
  const lines = [];
  let current = [];
  for (const s of samples) {
    const v = s[key];
    if (typeof v !== "number") {
      if (current.length) lines.push(current.join(" "));
      current = [];
      continue;
    }
    const x = ((s.time - t0) / (t1 - t0)) * w;
    const y = h - ((v - lo) / (hi - lo)) * h;
    current.push(`${x.toFixed(1)},${y.toFixed(1)}`);
  }
  if (current.length) lines.push(current.join(" "));
  return lines;
}

/** The spans [from, to] of time the valve was recorded open, closed by the next sample
 * that saw it closed (or the last sample). */
export function openSpans(samples) {
  const spans = [];
  let from = null;
  for (const s of samples) {
    if (s.valve_open && from === null) from = s.time;
    if (!s.valve_open && from !== null) {
      spans.push([from, s.time]);
      from = null;
    }
  }
  if (from !== null && samples.length) spans.push([from, samples[samples.length - 1].time]);
  return spans;
}

/** The index of the last sample taken at or before `t` (0 before the first). */
export function sampleAt(samples, t) {
  let lo = 0, hi = samples.length - 1, found = 0;
  while (lo <= hi) {
    const mid = (lo + hi) >> 1;
    if (samples[mid].time <= t) {
      found = mid;
      lo = mid + 1;
    } else {
      hi = mid - 1;
    }
  }
  return found;
}

/** The recorded path as segments in the robot's mm frame, each with whether glue flowed:
 * [{points: [[x, y], ...], open}], consecutive samples of one valve state joined. */
export function pathSegments(samples) {
  const segments = [];
  let last = null;
  for (const s of samples) {
    if (typeof s.x_mm !== "number" || typeof s.y_mm !== "number") continue;
    const point = [s.x_mm, s.y_mm];
    const open = Boolean(s.valve_open);
    if (!last || last.open !== open) {
      last = { points: last ? [last.points[last.points.length - 1], point] : [point], open };
      segments.push(last);
    } else {
      last.points.push(point);
    }
  }
  return segments;
}
