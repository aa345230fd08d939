// A few helpers to build the page's DOM without HTML strings (nothing is parsed as markup).

/** h("button", {class: "btn", onclick: f}, "text", child, ...) */
export function h(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs ?? {})) {
    if (value === null || value === undefined || value === false) continue;
    if (key.startsWith("on") && typeof value === "function") {
      node.addEventListener(key.slice(2), value);
    } else if (key === "dataset") {
      Object.assign(node.dataset, value);
    } else if (value === true) {
      node.setAttribute(key, "");
    } else {
      node.setAttribute(key, String(value));
    }
  }
  append(node, children);
  return node;
}

export function append(node, children) {
  for (const child of children.flat(Infinity)) {
    if (child === null || child === undefined || child === false) continue;
    node.appendChild(child instanceof Node ? child : document.createTextNode(String(child)));
  }
  return node;
}

/** Paragraphs of a plain text, split on blank lines. */
export function paragraphs(text) {
  return String(text)
    .split(/\n\s*\n/)
    .map((part) => part.replace(/\s+/g, " ").trim())
    .filter(Boolean)
    .map((part) => h("p", {}, part));
}

export const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

/** "two-rooms" -> "Two Rooms" */
export function environmentTitle(name) {
  return name
    .split("-")
    .map((word) => word.charAt(0).toUpperCase() + word.slice(1))
    .join(" ");
}

export function capitalise(text) {
  return text.charAt(0).toUpperCase() + text.slice(1);
}

/** "2026-11-26 10:42:07 UTC": how every time is written on the experimenter's pages (the
 * server writes the replica's the same way, ``format_time`` in routers/common.py). ``value`` is
 * a Date or an ISO 8601 text; one without a zone is UTC, as the server keeps times. */
export function formatTime(value) {
  if (value === null || value === undefined || value === "") return "";
  const text = String(value);
  const date = value instanceof Date ? value : new Date(/(Z|[+-]\d\d:?\d\d)$/.test(text) ? text : `${text}Z`);
  if (Number.isNaN(date.getTime())) return text;
  return `${date.toISOString().slice(0, 19).replace("T", " ")} UTC`;
}
