// The dashboard's line on each Prolific study: its status on Prolific (from the
// study.status.change webhook) and, when Prolific warned of a high return rate
// (study.has_high_return_rate), the warning with our own share of returns and their reasons.

import { getJSON } from "./api.js";
import { formatTime, h } from "./dom.js";

const REFRESH_MS = 10000;
const section = document.querySelector("#prolific-studies");

function percent(share) {
  return share === null ? "no one arrived yet" : `${Math.round(share * 100)} %`;
}

function warning(study) {
  const w = study.high_return_rate;
  const reasons = Object.entries(w.reasons).filter(([, n]) => n > 0).map(([why, n]) => `${why}: ${n}`);
  const extra = Object.keys(w.metadata).length ? ` Prolific's details: ${JSON.stringify(w.metadata)}.` : "";
  return h("p", { class: "prolific-warning", role: "alert", "data-high-return-rate": study.study_id },
    `⚠ Prolific warned of a high return rate at ${formatTime(w.warned_at)}. `,
    `Returned so far: ${w.returned} of ${w.arrived} (${percent(w.share_returned)})`,
    reasons.length ? ` (${reasons.join(", ")}).` : ".",
    extra);
}

// The server's own changes to the study (its concurrency and pauses held to its capacity).
function changes(study) {
  const shown = (study.changes || []).slice(0, 5);
  if (!shown.length) return null;
  return h("ul", { class: "prolific-changes", "data-prolific-changes": study.study_id },
    ...shown.map((c) => h("li", { "data-change": c.change },
      `${formatTime(c.at)}: `,
      c.change === "max_concurrent_submissions" ? `concurrency set to ${c.value}` : c.change === "PAUSE" ? "paused" : "started again",
      ` (${c.reason})`,
      c.outcome === "done" ? "" : ` - Prolific refused: ${c.outcome}`)));
}

function line(study) {
  const status = study.status
    ? [h("strong", { "data-study-status": study.status }, study.status), study.status_at ? ` since ${formatTime(study.status_at)}` : ""]
    : [h("span", { class: "muted", "data-study-status": "" }, "no status event from Prolific yet")];
  return h("div", { "data-prolific-study": study.study_id },
    h("p", {}, "Prolific study ", h("span", { class: "mono" }, study.study_id), ": ", ...status),
    study.high_return_rate ? warning(study) : null,
    changes(study));
}

// What is shown, so that a refresh with nothing new leaves the page (and the alert) alone.
let shown = null;

async function refresh() {
  try {
    const studies = await getJSON("/api/admin/prolific-studies");
    const text = JSON.stringify(studies);
    if (text === shown) return;
    shown = text;
    section.querySelector(".studies").replaceChildren(...studies.map(line));
    section.hidden = studies.length === 0;
  } catch (error) {
    shown = null;
    section.querySelector(".studies").replaceChildren(h("p", { class: "muted" }, `could not update: ${error.message}`));
    section.hidden = false;
  }
}

if (section) {
  await refresh();
  setInterval(refresh, REFRESH_MS);
}
