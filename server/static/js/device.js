// The device check before consent (the study file's [device_check]): one arrow key press asked
// for, the window's size shown as it changes, and what the study's pages need of the browser.
// The page reports what it measured; the server judges it (a window too small, no arrow key in
// the time given, a browser that lacks something) and may turn the participant away.

import { h } from "./dom.js";

const ARROWS = new Set(["ArrowUp", "ArrowDown", "ArrowLeft", "ArrowRight"]);

/** What the study's pages use that this browser lacks (the API's names). */
export function missingFeatures() {
  const missing = [];
  if (typeof window.fetch !== "function") missing.push("fetch");
  if (typeof window.HTMLDialogElement !== "function" || !("showModal" in window.HTMLDialogElement.prototype)) missing.push("dialog");
  if (typeof document.createElementNS !== "function" || !("createSVGPoint" in document.createElementNS("http://www.w3.org/2000/svg", "svg"))) missing.push("svg");
  return missing;
}

/** The window's size now, in CSS pixels. */
export function windowSize() {
  return { width: window.innerWidth, height: window.innerHeight };
}

/** The check's page, in ``container`` (a sheet): resolves with the report once an arrow key is
 * pressed, the participant says there are none, or ``needs.key_seconds`` pass. */
export function deviceCheck(container, needs) {
  const size = h("p", { class: "device-size", "data-device": "size" });
  const left = h("p", { class: "muted device-time" });
  const noKeys = h("button", { class: "btn", type: "button", "data-action": "no-arrow-keys" }, "My device has no arrow keys");
  const prompt = h("div", { class: "device-prompt", "aria-hidden": "true" }, "\u2190 \u2191 \u2192 \u2193");
  container.append(
    h("h1", {}, "Before you start: a check of your device"),
    h("p", { class: "lead" }, "This study is done with the arrow keys of a keyboard, in a browser window at least ",
      `${needs.min_width} \u00d7 ${needs.min_height} pixels.`),
    h("p", {}, "Make your window large enough (maximise it if you can), then press any arrow key: \u2190, \u2191, \u2192 or \u2193."),
    prompt, size, left, h("div", { class: "actions" }, noKeys));

  const showSize = () => {
    const { width, height } = windowSize();
    const enough = width >= needs.min_width && height >= needs.min_height;
    size.dataset.enough = String(enough);
    size.textContent = `Your window: ${width} \u00d7 ${height} pixels, ${enough ? "large enough" : "too small: please make it larger"}.`;
  };
  showSize();
  window.addEventListener("resize", showSize);

  return new Promise((resolve) => {
    const deadline = performance.now() + needs.key_seconds * 1000;
    let timer = null;
    const done = (arrowKey) => {
      window.removeEventListener("resize", showSize);
      document.removeEventListener("keydown", onKey);
      clearInterval(timer);
      noKeys.disabled = true;
      resolve({ arrow_key: arrowKey, ...windowSize(), missing: missingFeatures() });
    };
    const onKey = (event) => {
      if (!ARROWS.has(event.key)) return;
      event.preventDefault();
      done(true);
    };
    const tick = () => {
      const seconds = Math.max(0, Math.ceil((deadline - performance.now()) / 1000));
      left.textContent = `Waiting for an arrow key: ${seconds} s left.`;
      if (seconds === 0) done(false);
    };
    document.addEventListener("keydown", onKey);
    noKeys.addEventListener("click", () => done(false));
    tick();
    timer = setInterval(tick, 250);
  });
}
