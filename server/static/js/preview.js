// The MTurk preview's device check (nothing is sent: a preview creates nothing): the window's
// size and an arrow key press, so that a worker whose device cannot take part does not accept
// the HIT. The study checks the device again, and records it, before consent.

import { missingFeatures, windowSize } from "./device.js";

const section = document.querySelector(".device-preview");
const needs = { width: Number(section.dataset.minWidth), height: Number(section.dataset.minHeight) };
const size = section.querySelector('[data-device="size"]');
const keys = section.querySelector('[data-device="keys"]');
const verdict = section.querySelector('[data-device="verdict"]');
let pressed = false;

function judge() {
  const { width, height } = windowSize();
  const enough = width >= needs.width && height >= needs.height;
  size.dataset.enough = String(enough);
  size.textContent = `Your window: ${width} \u00d7 ${height} pixels, ${enough ? "large enough" : "too small"}.`;
  const missing = missingFeatures();
  if (!enough || missing.length) {
    verdict.dataset.verdict = "do-not-accept";
    verdict.textContent = missing.length
      ? "This browser cannot run the study: please do not accept this HIT."
      : "Your window is too small for the study: make it larger, or please do not accept this HIT.";
  } else if (pressed) {
    verdict.dataset.verdict = "ready";
    verdict.textContent = "Your device can take part.";
  } else {
    verdict.dataset.verdict = "waiting";
    verdict.textContent = "";
  }
}

document.addEventListener("keydown", (event) => {
  if (!event.key.startsWith("Arrow")) return;
  event.preventDefault();
  pressed = true;
  keys.textContent = "An arrow key was pressed: your keyboard works.";
  judge();
});
window.addEventListener("resize", judge);
judge();
