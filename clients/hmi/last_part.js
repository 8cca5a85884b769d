/* The last part: the verdict of the last spray run to end, its reasons and its
 * annotated image. Read from the journal (GET /operations, newest trajectory run
 * that ended), on each snapshot and whenever an operation ends (a state change out
 * of a busy state on /ws): the run's record is committed before that answer, so the
 * card shows the run that just ended. The verdict and its words are the server's
 * (`part` of the row, server/quality/part_verdict.py), the same the order card, the
 * KPIs, the CSV export, MQTT, OPC UA and the webhooks give the part. The image
 * (GET /runs/{run_id}/inspection.jpg) is asked for only when the inspection says it
 * kept one; any answer but an image (404: not kept, or a server without it) leaves
 * the card without a picture. */

import { AuthError, blobUrl, getJson } from "./api.js";
import { $, element, facts, number } from "./dom.js";
import { hmi } from "./store.js";

const RECENT_RUNS = 3; // the newest may still be running: the one before it has ended

let asked = 0; // the latest refresh wins when two overlap

/** What the card says of a run record (pure: no DOM): its `part` as the server judged
 * it (verdict good, defective or not_inspected; label; reasons), and the inspection's
 * figures when it was inspected. A row without `part` shows no verdict. */
export function describePart(run) {
  if (!run) return { verdict: "none", label: "no part yet", reasons: [], figures: [] };
  const note = `run ${run.outcome || "ended"}`;
  const part = run.part;
  if (!part || typeof part.verdict !== "string") {
    return { verdict: "none", label: "no verdict", note, reasons: [], figures: [] };
  }
  const reasons = Array.isArray(part.reasons) ? part.reasons.map(String) : [];
  const inspection = part.inspected && run.result ? run.result.inspection : null;
  if (!inspection) {
    return { verdict: part.verdict, label: String(part.label), note, reasons, figures: [] };
  }
  const mm = (value) => (typeof value === "number" ? `${number(value, 2)} mm` : "—");
  return {
    verdict: part.verdict,
    label: String(part.label),
    note,
    reasons,
    figures: [
      ["path deviation p95", mm(inspection.precision_p95_mm)],
      ["flow CV", typeof inspection.dispensing_cv_percent === "number"
        ? `${number(inspection.dispensing_cv_percent, 1)} %` : "—"],
      ["glue", typeof inspection.glue_ml === "number" ? `${number(inspection.glue_ml, 2)} ml` : "—"],
      ["vision residual", mm(inspection.vision_residual_mm)],
    ],
    image: inspection.image === true,
  };
}

export async function refreshLastPart() {
  if (!hmi.token) return;
  const ticket = ++asked;
  const card = document.querySelector(".card-part");
  try {
    const page = await getJson(`/operations?kind=trajectory&limit=${RECENT_RUNS}`);
    const run = (page.operations || []).find((r) => r.ended_at != null) || null;
    const image = run && describePart(run).image
      ? await blobUrl(`/runs/${encodeURIComponent(run.run_id)}/inspection.jpg`).catch(() => null)
      : null;
    if (ticket !== asked) {
      if (image) URL.revokeObjectURL(image);
      return;
    }
    renderPart(run, image);
    card.dataset.stale = "false";
  } catch (error) {
    if (!(error instanceof AuthError) && ticket === asked) card.dataset.stale = "true";
  }
}

function renderPart(run, image) {
  const part = describePart(run);
  const verdict = $("part-verdict");
  verdict.textContent = part.label;
  verdict.dataset.kind = { good: "ok", defective: "fault" }[part.verdict] || "";
  $("part").dataset.verdict = part.verdict;
  $("part").dataset.run = run ? run.run_id : "";
  // The whole id: its first part is the server process's, the same for every run of it.
  $("part-run").textContent = run ? `run ${run.run_id} · ${part.note}` : "";
  $("part-reasons").replaceChildren(...part.reasons.map((text) => element("li", "", text)));
  $("part-figures").replaceChildren(...(part.figures.length ? [facts(part.figures)] : []));
  if (hmi.partImage) URL.revokeObjectURL(hmi.partImage);
  hmi.partImage = image;
  const picture = $("part-image");
  picture.hidden = !image;
  if (image) {
    picture.src = image;
    picture.alt = `inspection of run ${run.run_id}: ${part.label}`;
  } else {
    picture.removeAttribute("src");
  }
  // The run's flight recording, replayed on its own page (run.html).
  const replay = $("part-replay");
  replay.hidden = !run;
  if (run) replay.href = `/hmi/run.html?run=${encodeURIComponent(run.run_id)}`;
  const note = $("part-image-note");
  note.hidden = Boolean(image) || !part.image;
  note.textContent = "no inspection image kept";
}
