/* A line of cells as their MQTT topics describe it: one row per cell, folded from
 * messages. Pure (no DOM, no network), read the same way as clients/line_model.py:
 *
 *   <prefix>/<cell_id>/status    retained JSON: status "online", or "offline" (a clean stop, the last will), time
 *   <prefix>/<cell_id>/state     retained JSON: state, since, stop_reason, run_id, ...
 *   <prefix>/<cell_id>/progress  JSON, where a run is (thinned by the cell): run_id, waypoint, total, fraction
 *   <prefix>/<cell_id>/kpis      retained JSON: the cell's GET /kpis body (oee.oee)
 *
 * A progress message belongs to its run: it is shown only while the cell's state
 * names that run, so a finished run's last waypoint never lingers beside IDLE. */

export const KINDS = ["status", "state", "progress", "kpis"];

export function splitTopic(prefix, topic) {
  const parts = topic.split("/");
  if (parts.length !== 3 || parts[0] !== prefix || !parts[1] || !KINDS.includes(parts[2])) {
    return null;
  }
  return { cellId: parts[1], kind: parts[2] };
}

export function emptyRow(cellId) {
  return {
    cellId, online: null, state: null, since: null, stopReason: null, runId: null,
    workpieceId: null, progress: null, oee: null,
  };
}

function jsonObject(text) {
  if (text === "") return {};  // a retained message cleared
  try {
    const value = JSON.parse(text);
    return value && typeof value === "object" && !Array.isArray(value) ? value : null;
  } catch {
    return null;
  }
}

const ratio = (value) => (typeof value === "number" && isFinite(value) ? value : null);

/** Fold one message into `line` (a Map of cell id → row); false if it is not a cell's. */
export function applyMessage(line, prefix, topic, text) {
  const found = splitTopic(prefix, topic);
  if (!found) return false;
  const row = line.get(found.cellId) ?? emptyRow(found.cellId);
  if (found.kind === "status") {
    // JSON with `status` and `time`; a cell of an earlier release sends the bare word.
    let word = text.trim();
    if (word.startsWith("{")) word = jsonObject(word)?.status ?? null;
    row.online = word === "online" ? true : word === "offline" ? false : null;
  } else {
    const body = jsonObject(text);
    if (body === null) return false;
    if (found.kind === "state") {
      row.state = typeof body.state === "string" ? body.state : null;
      row.since = ratio(body.since);
      row.stopReason = body.stop_reason && typeof body.stop_reason === "object" ? body.stop_reason : null;
      row.runId = body.run_id ?? null;
      row.workpieceId = body.workpiece_id ?? null;
    } else if (found.kind === "progress") {
      row.progress = Object.keys(body).length ? body : null;
    } else {
      row.oee = body.oee && typeof body.oee === "object" ? ratio(body.oee.oee) : null;
    }
  }
  line.set(found.cellId, row);
  return true;
}

/** The progress of the cell's current run, or null. */
export function shownProgress(row) {
  const progress = row.progress;
  if (!progress || row.runId === null || progress.run_id !== row.runId) return null;
  return progress;
}

/** The cells in the order of their ids. */
export function sortedRows(line) {
  return [...line.values()].sort((a, b) => (a.cellId < b.cellId ? -1 : a.cellId > b.cellId ? 1 : 0));
}

export function stopReasonText(reason) {
  if (!reason) return "";
  const { code, message } = reason;
  return code && message ? `${code}: ${message}` : String(code || message || "");
}
