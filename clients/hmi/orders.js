/* The order card: the active production order (state, good/defective of its
 * quantity, why it is held) and its commands: start an order, close it, resume
 * a held one. Refreshed with the other panels (GET /orders) and after each
 * command. The server runs the order's parts by itself; this card only asks. */

import { AuthError, api, errorText, getJson } from "./api.js";
import { $, element, facts } from "./dom.js";
import { showMessage } from "./render.js";
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
    const children = [facts(rows)];
    if (shown.reason) children.push(element("p", "order-reason small", shown.reason));
    body.replaceChildren(...children);
    body.dataset.orderId = shown.order_id;
  }
  $("order-close").disabled = !isActive(shown);
  $("order-resume").disabled = shown?.state !== "held";
}

// One order request at a time: a double tap on "Start order" made two orders, both run.
let sending = false;

async function send(method, path, body, label) {
  if (sending) return;
  sending = true;
  const buttons = ["order-start", "order-close", "order-resume"].map((id) => $(id));
  buttons.forEach((button) => { button.disabled = true; });
  try {
    const response = await api(method, path, body);
    const ok = response.status === 200 || response.status === 201;
    showMessage(ok ? "ok" : response.status === 409 ? "refused" : "error",
      `${label}: ${response.status}${ok ? "" : `: ${await errorText(response)}`}`);
  } catch (error) {
    if (!(error instanceof AuthError)) showMessage("error", `${label}: ${error.message}`);
  } finally {
    await refreshOrders(); // the card shows the new order before Start is offered again
    sending = false;
    $("order-start").disabled = false;
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
  send("POST", "/orders", { workpiece_id, quantity }, "order");
}

/** Wire the card's form and buttons (once, at start). */
export function initOrders() {
  $("order-form").addEventListener("submit", startOrder);
  $("order-close").addEventListener("click", () => {
    if (hmi.order) send("POST", `/orders/${hmi.order.order_id}/close`, undefined, "close order");
  });
  $("order-resume").addEventListener("click", () => {
    if (hmi.order) send("POST", `/orders/${hmi.order.order_id}/resume`, undefined, "resume order");
  });
}
