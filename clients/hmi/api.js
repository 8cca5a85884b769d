/* HTTP to the cell's API: every request carries the session's token; a 401 ends
 * the session (the token is unknown or was revoked) and throws AuthError, which
 * callers let pass silently: the login form already says why. */

import { hmi } from "./store.js";

export class AuthError extends Error {}

let onUnauthorized = () => {};

/** What to do when the server answers 401: sign out, with the server's message. */
export function whenUnauthorized(handler) {
  onUnauthorized = handler;
}

export async function api(method, path, body, extra) {
  const headers = { ...(extra || {}), Authorization: `Bearer ${hmi.token}` };
  const init = { method, headers, cache: "no-store" };
  if (body !== undefined) {
    headers["Content-Type"] = "application/json";
    init.body = JSON.stringify(body);
  }
  const response = await fetch(path, init);
  if (response.status === 401) {
    const message = await errorText(response);
    onUnauthorized(message);
    throw new AuthError(message);
  }
  return response;
}

export async function getJson(path) {
  const response = await api("GET", path);
  if (!response.ok) throw new Error(await errorText(response));
  return response.json();
}

export async function errorText(response) {
  try {
    const body = await response.clone().json();
    return body.message || body.detail || JSON.stringify(body);
  } catch {
    return (await response.text()) || response.statusText;
  }
}

export async function blobUrl(path) {
  const response = await api("GET", path);
  if (!response.ok) return null;
  return URL.createObjectURL(await response.blob());
}

/** A candidate token, tried on GET /state before the session starts with it. */
export async function tryToken(token) {
  const response = await fetch("/state", {
    headers: { Authorization: `Bearer ${token}` },
    cache: "no-store",
  });
  if (response.ok) return { ok: true, view: await response.json() };
  return { ok: false, message: await errorText(response) };
}
