/* Who is signed in, and what their token may do (GET /me): the page offers only that.
 *
 * GET /me names the token, its role, each command with the role it needs and the pages
 * the role may open. A command the role may never send is not a button on this page
 * (hidden); one it may send is live only when the state allows it too
 * (render.js: renderCommands). When the cell waits for a command the role lacks (a
 * reset after a stop needs maintenance), `callFor` says whom to call, in words. */

import { getJson } from "./api.js";
import { $ } from "./dom.js";
import { hmi } from "./store.js";

/** Fetch GET /me into `hmi.me` and draw what depends on the role. */
export async function refreshMe() {
  const me = await getJson("/me");
  hmi.me = {
    name: me.name,
    role: me.role,
    pages: me.pages,
    needs: Object.fromEntries(me.commands.map((c) => [c.name, c.role])),
    commands: new Set(me.commands.filter((c) => c.allowed).map((c) => c.name)),
  };
  applyRole();
  return hmi.me;
}

/** Whether the signed-in role may send `command` (its state aside); unknown: no. */
export function roleAllows(command) {
  return Boolean(hmi.me && hmi.me.commands.has(command));
}

/** The words for an available command the role lacks, or "" (pure on `me`).
 * "Call maintenance to reset: needs the maintenance role". */
export function callFor(me, available) {
  if (!me) return "";
  const lacking = available.filter((name) => !me.commands.has(name) && me.needs[name]);
  return lacking
    .map((name) => `Call ${me.needs[name]} to ${name.replaceAll("-", " ")}: ` +
      `needs the ${me.needs[name]} role`)
    .join(". ");
}

function applyRole() {
  const me = hmi.me;
  $("who").textContent = me ? `${me.name} · ${me.role}` : "";
  $("who").dataset.role = me ? me.role : "";
  const setup = $("nav-setup");
  if (setup) setup.hidden = !(me && me.pages.setup);
  for (const button of document.querySelectorAll("[data-command]")) {
    // A command this role may never send is not offered at all.
    button.hidden = !roleAllows(button.dataset.command);
  }
}

/** Forget the signed-in user (sign-out): nothing of theirs stays on the page. */
export function forgetMe() {
  hmi.me = null;
  $("who").textContent = "";
  const setup = $("nav-setup");
  if (setup) setup.hidden = true;
}
