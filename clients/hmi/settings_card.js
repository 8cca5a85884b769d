/* The Settings card: the settings a change applies to at once (GET /settings names
 * them in `runtime_settings`), each with its value in force and where it comes from,
 * and a Save that sends the edited ones (PATCH /settings). A change is saved by the
 * server and stays over a restart; the card says so, or says why it was refused.
 *
 * Shown only to a token that may read the settings: GET /settings answers 403 to
 * any other role, and the card then stays hidden. Loaded when the session starts and
 * again after each save (a setting changes nowhere else but here, gluectl and the API).
 */

import { AuthError, api, errorText } from "./api.js";
import { $, element } from "./dom.js";

const SOURCE_WORDS = {
  runtime: "changed here",
  "command line": "command line",
  environment: "environment",
  file: "config file",
  default: "default",
};

// What the card shows: the values in force when it was loaded, by name.
let shown = {};

/** Read the settings and draw the card; hide it for a role that may not see them. */
export async function refreshSettings() {
  const card = document.querySelector(".card-settings");
  try {
    const response = await api("GET", "/settings");
    if (response.status === 403) {
      card.hidden = true;
      return;
    }
    if (!response.ok) throw new Error(await errorText(response));
    renderSettings(await response.json());
    card.hidden = false;
    card.dataset.stale = "false";
  } catch (error) {
    if (!(error instanceof AuthError)) card.dataset.stale = "true";
  }
}

function inputFor(name, value) {
  let input;
  if (typeof value === "boolean") {
    input = element("input");
    input.type = "checkbox";
    input.checked = value;
  } else if (value !== null && typeof value === "object") {
    // A list or a structure (the maintenance items): shown, changed with gluectl or the API.
    input = element("input");
    input.type = "text";
    input.readOnly = true;
    input.value = JSON.stringify(value);
    input.title = "change it with gluectl settings set or PATCH /settings";
  } else if (name === "logging_level") {
    input = element("select");
    for (const level of ["DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL"]) {
      const option = element("option", "", level);
      option.value = level;
      input.append(option);
    }
    input.value = value;
  } else {
    input = element("input");
    input.type = "number";
    input.step = "any";
    input.value = String(value);
  }
  input.id = `setting-${name}`;
  input.dataset.setting = name;
  input.className = "setting-input";
  return input;
}

function renderSettings(data) {
  shown = {};
  const rows = [];
  for (const name of data.runtime_settings || []) {
    shown[name] = data[name];
    const label = element("label", "setting-name", name);
    label.htmlFor = `setting-${name}`;
    const source = element("span", "setting-source muted small",
      SOURCE_WORDS[data.sources?.[name]] || data.sources?.[name] || "");
    source.dataset.source = data.sources?.[name] || "";
    const row = element("div", "setting-row");
    row.dataset.setting = name;
    row.append(label, inputFor(name, data[name]), source);
    rows.push(row);
  }
  $("settings-list").replaceChildren(...rows);
}

/** The edited settings: each input whose value differs from the one shown. */
function edited() {
  const change = {};
  for (const input of document.querySelectorAll("#settings-list .setting-input")) {
    const name = input.dataset.setting;
    if (input.readOnly) continue;
    let value;
    if (input.type === "checkbox") value = input.checked;
    else if (input.tagName === "SELECT") value = input.value;
    else value = input.value.trim() === "" ? null : Number(input.value);
    if (value !== shown[name]) change[name] = value;
  }
  return change;
}

function say(kind, text) {
  const note = $("settings-message");
  note.dataset.kind = kind;
  note.textContent = text;
  note.hidden = false;
}

async function save(event) {
  event.preventDefault();
  const change = edited();
  if (!Object.keys(change).length) return say("ok", "Nothing to save: no value was changed.");
  const button = $("settings-save");
  button.disabled = true;
  try {
    const response = await api("PATCH", "/settings", change);
    if (response.ok) {
      const changed = (await response.json()).changed || {};
      const words = Object.entries(changed).map(([name, c]) => `${name} ${c.old} → ${c.new}`);
      say("ok", words.length
        ? `Saved: ${words.join(", ")}. It stays over a restart.`
        : "Nothing changed: each value was in force already.");
    } else {
      say("refused", `Not saved: ${await errorText(response)}`);
    }
  } catch (error) {
    if (!(error instanceof AuthError)) say("error", `Not saved: ${error.message}`);
  } finally {
    button.disabled = false;
    await refreshSettings();
  }
}

/** Wire the card's form (once, at start). */
export function initSettings() {
  $("settings-form").addEventListener("submit", save);
}
