// A small line chart in SVG: normalised return (0 to 1) against episodes, step lines with an
// optional band (± one standard error), dotted thresholds, for the live pages.

import { h } from "./dom.js";
import { svg } from "./grid.js";

const W = 420, H = 220, LEFT = 40, RIGHT = 12, TOP = 12, BOTTOM = 34;

/** series: [{label, colour, xs, ys, lows?, highs?}] (ys may hold null: no value there). */
export function stepChart({ series, thresholds = [], label, xLabel = "Episodes" }) {
  const most = Math.max(1, ...series.flatMap((s) => s.xs));
  const x = (v) => LEFT + (v / most) * (W - LEFT - RIGHT);
  const y = (v) => TOP + (1 - Math.max(0, Math.min(1.05, v)) / 1.05) * (H - TOP - BOTTOM);
  const root = svg("svg", { viewBox: `0 0 ${W} ${H}`, class: "step-chart", role: "img", "aria-label": label });
  const axes = svg("g", { class: "chart-axes" }, root);
  svg("line", { x1: LEFT, y1: y(0), x2: W - RIGHT, y2: y(0) }, axes);
  svg("line", { x1: LEFT, y1: y(0), x2: LEFT, y2: TOP }, axes);
  for (const tick of [0, 0.5, 1]) {
    const t = svg("text", { x: LEFT - 6, y: y(tick) + 4, "text-anchor": "end" }, axes);
    t.textContent = tick.toFixed(1);
  }
  for (const tick of [0, most]) {
    const t = svg("text", { x: x(tick), y: H - BOTTOM + 16, "text-anchor": "middle" }, axes);
    t.textContent = String(tick);
  }
  const name = svg("text", { x: (LEFT + W - RIGHT) / 2, y: H - 4, "text-anchor": "middle" }, axes);
  name.textContent = xLabel;
  for (const threshold of thresholds) {
    svg("line", { class: "chart-threshold", x1: LEFT, y1: y(threshold), x2: W - RIGHT, y2: y(threshold) }, root);
  }
  for (const s of series) {
    // A step function: each value holds until the next count.
    const steps = (values) => {
      const parts = [];
      for (let i = 0; i < s.xs.length; i++) {
        if (values[i] === null || values[i] === undefined) continue;
        const next = i + 1 < s.xs.length ? s.xs[i + 1] : s.xs[i];
        parts.push([x(s.xs[i]), y(values[i])], [x(next), y(values[i])]);
      }
      return parts;
    };
    if (s.lows && s.highs) {
      const lows = s.lows.map((v, i) => (v === null || s.ys[i] === null ? s.ys[i] : v));
      const highs = s.highs.map((v, i) => (v === null || s.ys[i] === null ? s.ys[i] : v));
      const top = steps(highs), bottom = steps(lows).reverse();
      if (top.length) svg("polygon", { class: "chart-band", fill: s.colour, points: [...top, ...bottom].map((p) => p.join(",")).join(" ") }, root);
    }
    const line = steps(s.ys);
    if (line.length) {
      svg("polyline", { class: "chart-line", stroke: s.colour, points: line.map((p) => p.join(",")).join(" "), "data-series": s.label, "data-last": String(s.ys[s.ys.length - 1]) }, root);
    }
  }
  return root;
}

/** The chart's legend: a swatch and a text per series. */
export function legend(series) {
  return h("ul", { class: "chart-legend" }, series.map((s) =>
    h("li", {}, h("span", { class: "chart-swatch", style: `background:${s.colour}`, "aria-hidden": "true" }), s.text ?? s.label)));
}
