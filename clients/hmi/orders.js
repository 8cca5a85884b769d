/* The order card: the active production order (state, good/defective of its
 * quantity, why it is held) and its commands: start an order, close it, resume
 * a held one. Refreshed with the other panels (GET /orders), after each command
 * and on each change of state. The server runs the order's parts by itself; this
 * card only asks. The active order's state, its good count and what to do next are
 * also in the left column (`#state-order`), on the first screen of every panel.
 *
 * A button is live only where the server would accept it: the role may (GET /me),
 * and for a start or a resume the cell could start a part now. A new order carries an
 * Idempotency-Key, so the server makes one order even if the request is sent twice. */

import { AuthError, api, errorText, getJson } from "./api.js";
import { $, element, facts } from "./dom.js";
import { showMessage } from "./render.js";
import { roleAllows } from "./role.js";
import { hmi } from "./store.js";

/** Running, held or queued: an order the cell still works through or will. */
function isActive(order) {
  return Boolean(order) && ["running", "held", "queued"].includes(order.state);
}

/** The active order, or the newest one, as the card shows it. */
export async function refreshOrders() {
  const card = document.querySelector(".card-order");
  try {
    renderOrders(await getJson("/orders"));
    card.dataset.stale = "false";
  } catch (error) {
    if (!(error instanceof AuthError)) card.dataset.stale = "true";
  }
}

function renderOrders(listing) {
  const shown =
    listing.orders.find((o) => o.order_id === listing.active) || listing.orders[0] || null;
  hmi.order = shown;
  const pill = $("order-state");
  pill.textContent = shown ? shown.state : "none";
  pill.dataset.kind = shown?.state === "held" ? "fault" : shown?.state === "running" ? "ok" : "";
  const body = $("order");
  if (!shown) {
    body.replaceChildren(element("p", "muted small", "No production order yet."));
  } else {
    const rows = [
      ["Order", shown.order_id],
      ["Workpiece", shown.workpiece_id],
      ["Good", `${shown.good} / ${shown.quantity}`],
      ["Defective", `${shown.defective} (${shown.defects_in_row} in a row)`],
    ];
    // Parts nobody inspected count toward the quantity too: say how many, in the same words.
    if (shown.not_inspected) {
      rows.splice(2, 1, ["Good", `${shown.good} + ${shown.not_inspected} not inspected / ${shown.quantity}`]);
    }
    const children = [facts(rows)];
    if (shown.reason) children.push(element("p", "order-reason small", shown.reason));
    body.replaceChildren(...children);
    body.dataset.orderId = shown.order_id;
  }
  renderOrderButtons();
}

/** What the operator does next with `order`, the cell in `state` (pure). */
export function nextAction(order, state) {
  if (!order) return "";
  if (order.state === "running") {
    if (state === "PAUSED") return "the cell is paused: Resume continues the part and the order";
    return "parts start by themselves";
  }
  if (order.state === "held") {
    return state === "ERROR" ? "reset the cell, then Resume order" : "Resume order to continue";
  }
  if (order.state === "queued") return "starts once the order before it ends";
  return "";
}

/** The active order in the left column: state, good of quantity, what to do next. */
function renderOrderSummary() {
  const order = hmi.order && isActive(hmi.order) ? hmi.order : null;
  const box = $("state-order");
  box.hidden = !order;
  if (!order) return;
  box.dataset.state = order.state;
  const next = nextAction(order, hmi.view?.state);
  $("state-order-text").textContent =
    `Order ${order.order_id} · ${order.state} · Good ${order.good}` +
    (order.not_inspected ? ` + ${order.not_inspected} not inspected` : "") +
    ` of ${order.quantity}` +
    (next ? ` · next: ${next}` : "");
}

/** Each order button live only where the server would accept it now. */
export function renderOrderButtons() {
  const order = hmi.order;
  const may = roleAllows("start"); // the orders' routes need the role a start needs
  const state = hmi.view?.state;
  const canStart = new Set(hmi.view?.available_commands || []).has("start");
  const live = hmi.live && !sending;
  // A new order starts now (the cell must be able to start a part) or queues behind one.
  $("order-start").disabled = !live || !may || (!isActive(order) && !canStart);
  $("order-close").disabled = !live || !may || !isActive(order);
  $("order-resume").disabled = !live || !may || order?.state !== "held" || state !== "IDLE";
  $("state-order-resume").hidden = $("order-resume").disabled;
  renderOrderSummary();
}

/** A key for one order the operator asked for: the same on a resend of that request. */
function newKey() {
  const bytes = crypto.getRandomValues(new Uint8Array(16)); // also where randomUUID is not
  return Array.from(bytes, (b) => b.toString(16).padStart(2, "0")).join("");
}

// One order request at a time: a double tap on "Start order" made two orders, both run.
let sending = false;

async function send(method, path, body, done, headers) {
  if (sending) return;
  sending = true;
  renderOrderButtons();
  try {
    const response = await api(method, path, body, headers);
    if (response.ok) {
      showMessage("ok", done((await response.json()).order || {}));
    } else {
      showMessage(response.status === 409 ? "refused" : "error", await errorText(response));
    }
  } catch (error) {
    if (!(error instanceof AuthError)) showMessage("error", error.message);
  } finally {
    await refreshOrders(); // the card shows the new order before Start is offered again
    sending = false;
    renderOrderButtons();
  }
}

function startOrder(event) {
  event.preventDefault();
  if (sending) return;
  const workpiece_id = $("order-workpiece").value.trim();
  const quantity = Number($("order-quantity").value);
  // With an order active a new one is queued behind it: asked first, so that a second
  // tap a moment after the first (the answer takes milliseconds) does not make one.
  const queue = `Order ${hmi.order?.order_id} is ${hmi.order?.state}. Queue another order ` +
    `of ${quantity} × ${workpiece_id} behind it?`;
  if (isActive(hmi.order) && !window.confirm(queue)) return;
  const started = (order) => order.state === "queued"
    ? `Order ${order.order_id} queued: ${quantity} × ${workpiece_id}`
    : `Order ${order.order_id} started: ${quantity} × ${workpiece_id}`;
  send("POST", "/orders", { workpiece_id, quantity }, started, { "Idempotency-Key": newKey() });
}

/** Wire the card's form and buttons (once, at start). */
export function initOrders() {
  hmi.renderHooks.push(renderOrderButtons);
  $("order-form").addEventListener("submit", startOrder);
  $("order-close").addEventListener("click", () => {
    if (hmi.order) {
      send("POST", `/orders/${hmi.order.order_id}/close`, undefined,
        (order) => `Order ${order.order_id} closed`);
    }
  });
  const resume = () => {
    if (hmi.order) {
      send("POST", `/orders/${hmi.order.order_id}/resume`, undefined,
        (order) => `Order ${order.order_id} resumed`);
    }
  };
  $("order-resume").addEventListener("click", resume);
  $("state-order-resume").addEventListener("click", resume);
}
