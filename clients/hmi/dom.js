/* Small DOM and text helpers; the text ones (numbers, durations, times) are pure. */

export const $ = (id) => document.getElementById(id);

export function element(tag, className, text) {
  const node = document.createElement(tag);
  if (className) node.className = className;
  if (text !== undefined) node.textContent = text;
  return node;
}

export function facts(rows) {
  const list = element("dl", "facts");
  for (const [term, value, mark] of rows) {
    const item = element("div", `fact ${mark || ""}`.trim());
    item.append(element("dt", "", term), element("dd", "", value));
    list.append(item);
  }
  return list;
}

export function number(value, digits) {
  return typeof value === "number" ? value.toFixed(digits) : "—";
}

export function percent(value) {
  return typeof value === "number" ? `${(value * 100).toFixed(1)} %` : "—";
}

export function duration(seconds) {
  if (typeof seconds !== "number" || !isFinite(seconds)) return "—";
  const s = Math.max(0, Math.floor(seconds));
  const h = Math.floor(s / 3600), m = Math.floor((s % 3600) / 60), rest = s % 60;
  const two = (n) => String(n).padStart(2, "0");
  return h ? `${h}:${two(m)}:${two(rest)}` : `${two(m)}:${two(rest)}`;
}

/** A span of time with its unit, for a figure that stands alone (a KPI tile):
 * "52 s", "14 min", "3.5 h", "2.1 d". `duration`'s "00:52" does not say m:ss or h:mm. */
export function span(seconds) {
  if (typeof seconds !== "number" || !isFinite(seconds)) return "—";
  const s = Math.max(0, seconds);
  if (s < 90) return `${Math.round(s)} s`;
  if (s < 90 * 60) return `${Math.round(s / 60)} min`;
  if (s < 48 * 3600) return `${(s / 3600).toFixed(1)} h`;
  return `${(s / 86400).toFixed(1)} d`;
}

export function clockTime(unixSeconds) {
  if (typeof unixSeconds !== "number") return "—";
  return new Date(unixSeconds * 1000).toLocaleTimeString([], { hour12: false });
}
