/* The marker layout panel of the Set-up page: jog the robot over a marker, teach
 * its position, correct a value by hand, apply the layout once all nine are there.
 *
 * Self-contained: `mountMarkerLayout(section, jogBox)` builds the panel inside
 * <section id="marker-layout">, its jog controls in `jogBox` (beside the camera, so the
 * technician sees both on one screen), and keeps it current from GET /calibration/markers.
 * Jog and Teach are live only when the server would accept them: the role may
 * (`allows`, from GET /state's `may`), the cell is IDLE and the robot stands still.
 * Every change goes through the API (POST /jog, POST /calibration/markers/draft/{n}/teach,
 * PUT /calibration/markers/draft/{n}, POST /calibration/markers/apply); the server's
 * refusals (409 not IDLE, 422 naming the marker and field) are shown as they come.
 */

import { api, errorText, getJson, AuthError } from "./api.js";
import { element, number } from "./dom.js";

const LAYOUT = "/calibration/markers";
const STEPS_MM = [0.1, 1, 5, 10, 50];
const REFRESH_MS = 1000;
const SETTLE_POLL_MS = 150;
const SETTLE_LIMIT_MS = 60000;

export function mountMarkerLayout(section, jogBox, allows) {
  const panel = new MarkerPanel(section, jogBox, allows);
  panel.refresh();
  const timer = setInterval(() => panel.refresh(), REFRESH_MS);
  return { unmount: () => clearInterval(timer), renderControls: () => panel.renderControls() };
}

class MarkerPanel {
  constructor(section, jogBox, allows) {
    this.section = section;
    this.allows = allows; // (command) => whether the role may send it in this state
    this.layout = null;
    this.busy = false;
    section.replaceChildren();
    section.append(element("h2", "", "Marker layout"));
    this.position = element("p", "marker-position", "robot: —");
    this.position.id = "marker-robot-position";
    jogBox.replaceChildren(element("h2", "card-title", "Jog"), this.position, this.buildJog());
    this.table = element("table", "marker-table");
    this.table.id = "marker-table";
    this.section.append(this.table);
    this.apply = element("button", "btn", "Apply layout");
    this.apply.id = "marker-apply";
    this.apply.addEventListener("click", () => this.act("POST", `${LAYOUT}/apply`));
    this.source = element("span", "marker-source", "");
    this.message = element("p", "marker-message", "");
    this.message.id = "marker-message";
    this.message.setAttribute("role", "status");
    this.section.append(this.apply, this.source, this.message);
  }

  buildJog() {
    const box = element("div", "marker-jog");
    this.step = element("select");
    this.step.id = "jog-step";
    this.step.setAttribute("aria-label", "jog step (mm)");
    for (const mm of STEPS_MM) {
      const option = element("option", "", `${mm} mm`);
      option.value = String(mm);
      if (mm === 5) option.selected = true;
      this.step.append(option);
    }
    box.append(element("span", "jog-label", "step"), this.step);
    this.jogButtons = [];
    for (const axis of ["x", "y", "z"]) {
      for (const sign of [-1, 1]) {
        const label = `${axis}${sign < 0 ? "−" : "+"}`;
        const button = element("button", "btn jog", label);
        button.dataset.jog = `${axis}${sign < 0 ? "-" : "+"}`;
        button.addEventListener("click", () => this.jog(axis, sign));
        this.jogButtons.push(button);
        box.append(button);
      }
    }
    return box;
  }

  async refresh() {
    if (this.busy) return;
    try {
      this.render(await getJson(LAYOUT));
    } catch (error) {
      if (!(error instanceof AuthError)) this.say(String(error.message || error));
    }
  }

  render(layout) {
    this.layout = layout;
    const robot = layout.robot || {};
    const p = robot.position;
    const where = Array.isArray(p)
      ? `x ${number(p[0], 2)}  y ${number(p[1], 2)}  z ${number(p[2], 2)} mm`
      : "—";
    this.position.textContent = `robot: ${where}${robot.moving ? " (moving)" : ""} · ${layout.state}`;
    for (const option of this.step.options) {
      option.disabled = Number(option.value) > layout.jog.max_step_mm;
    }
    this.source.textContent = ` in force: ${layout.source === "taught" ? "taught layout" : "settings"}`;
    const editing = this.table.contains(document.activeElement);
    if (!editing) this.renderTable(layout);
    this.renderControls();
  }

  /** Jog and Teach live only when they would be accepted: the role may, the cell is
   * IDLE, the robot stands still and nothing of ours is on its way. */
  renderControls() {
    const layout = this.layout;
    const still = Boolean(layout) && layout.state === "IDLE" && !(layout.robot || {}).moving;
    const jog = still && !this.busy && this.allows("jog");
    for (const button of this.jogButtons) button.disabled = !jog;
    this.step.disabled = !jog;
    const teach = still && !this.busy && this.allows("teach");
    for (const button of this.table.querySelectorAll("[data-teach]")) button.disabled = !teach;
  }

  renderTable(layout) {
    const head = element("tr");
    for (const title of ["marker", "in force x, y (mm)", "draft x (mm)", "draft y (mm)", "how", ""]) {
      head.append(element("th", "", title));
    }
    const rows = [head];
    layout.in_force.forEach(([x, y], marker) => {
      const draft = layout.draft[marker];
      const row = element("tr");
      row.dataset.marker = String(marker);
      const inputs = ["x_mm", "y_mm"].map((field) => {
        const input = element("input");
        input.type = "number";
        input.step = "0.1";
        input.name = `marker-${marker}-${field}`;
        input.setAttribute("aria-label", `marker ${marker} ${field}`);
        input.value = draft ? String(draft[field]) : "";
        input.addEventListener("change", () => this.type(marker, inputs));
        return input;
      });
      const teach = element("button", "btn btn-small", "Teach");
      teach.dataset.teach = String(marker);
      teach.addEventListener("click", () => this.act("POST", `${LAYOUT}/draft/${marker}/teach`));
      const cells = [
        element("td", "", String(marker)),
        element("td", "", `${number(x, 1)}, ${number(y, 1)}`),
        element("td"),
        element("td"),
        element("td", "how", draft ? draft.how : "missing"),
        element("td"),
      ];
      cells[2].append(inputs[0]);
      cells[3].append(inputs[1]);
      cells[5].append(teach);
      row.append(...cells);
      rows.push(row);
    });
    this.table.replaceChildren(...rows);
    this.apply.disabled = layout.missing.length > 0;
  }

  async type(marker, inputs) {
    const [x, y] = inputs.map((input) => input.value);
    if (x === "" || y === "") return; // both are needed; wait for the other one
    await this.act("PUT", `${LAYOUT}/draft/${marker}`, { x_mm: Number(x), y_mm: Number(y) });
  }

  async jog(axis, sign) {
    const distance = sign * Number(this.step.value);
    const response = await this.send("POST", "/jog", { axis, distance_mm: distance });
    if (!response) return;
    this.say(`jog ${axis} ${distance > 0 ? "+" : ""}${distance} mm`);
    await this.settle();
  }

  /** Follow the jog until the robot stands, so Teach reads where it stopped. */
  async settle() {
    const until = performance.now() + SETTLE_LIMIT_MS;
    while (performance.now() < until) {
      const layout = await getJson(LAYOUT);
      this.render(layout);
      if (!layout.robot.moving) return;
      await new Promise((resolve) => setTimeout(resolve, SETTLE_POLL_MS));
    }
  }

  async act(method, path, body) {
    const response = await this.send(method, path, body);
    if (!response) return;
    this.table.replaceChildren(); // drop any edit in progress: show what the server kept
    this.render(await response.json());
    this.say(method === "POST" && path.endsWith("/apply") ? "layout applied" : "saved in the draft");
  }

  async send(method, path, body) {
    this.busy = true;
    this.renderControls();
    try {
      const response = await api(method, path, body);
      if (!response.ok) {
        this.say(`refused: ${await errorText(response)}`);
        return null;
      }
      return response;
    } catch (error) {
      if (!(error instanceof AuthError)) this.say(String(error.message || error));
      return null;
    } finally {
      this.busy = false;
      this.renderControls();
    }
  }

  say(text) {
    this.message.textContent = text;
  }
}
