// The live dashboard: who is where (the funnel, pushed by the server as server-sent events),
// the learner updates' queue, and the learning so far per environment and learner. Nothing is
// polled: each view is one EventSource, which reconnects by itself.

import { environmentTitle, formatTime, h } from "./dom.js";
import { legend, stepChart } from "./charts.js";

const API = "/api/admin/live";
const learners = JSON.parse(document.getElementById("learner-colours").textContent);
const stageLabels = JSON.parse(document.getElementById("stage-labels").textContent);
const $ = (selector) => document.querySelector(selector);

function duration(seconds) {
  if (seconds === null || seconds === undefined) return "";
  if (seconds < 60) return `${Math.round(seconds)} s`;
  if (seconds < 3600) return `${Math.floor(seconds / 60)} min ${Math.round(seconds % 60)} s`;
  return `${(seconds / 3600).toFixed(1)} h`;
}

function stageText(row) {
  if (row.stage === "agent") return `Teaching agent ${row.agent} of ${row.agents}`;
  return stageLabels[row.stage] ?? row.stage;
}

function showFunnel(snapshot) {
  const stamp = $("#funnel-at");
  stamp.dataset.live = "on";
  stamp.textContent = `as of ${formatTime(snapshot.at)}`;
  const items = Object.entries(snapshot.stages).map(([stage, count]) => {
    let label = stageLabels[stage] ?? stage;
    if (stage === "agent") {
      const parts = Object.entries(snapshot.agents).map(([k, n]) => `${n} at agent ${k}`);
      label = `Teaching an agent${parts.length ? ` (${parts.join(", ")})` : ""}`;
    }
    return h("li", { "data-stage": stage, "data-count": count }, h("span", { class: "count" }, String(count)), h("span", { class: "label" }, label));
  });
  $("#funnel").replaceChildren(...items);
  $("#funnel-notes").replaceChildren(
    h("span", { "data-live": "total" }, `${snapshot.participants_total} participant${snapshot.participants_total === 1 ? "" : "s"} in all; `),
    h("span", { "data-live": "idle" }, `${snapshot.idle} idle for more than 5 minutes; `),
    h("span", { "data-live": "failed" }, `${snapshot.failed_a_check} failed an attention check.`),
    snapshot.listed_of > snapshot.participants.length ? ` The ${snapshot.participants.length} there longest are listed.` : "");
  const rows = snapshot.participants.map((row) =>
    h("tr", { "data-participant": row.participant_id, "data-stage": row.stage },
      h("td", {}, String(row.participant_id)),
      h("td", {}, stageText(row)),
      h("td", {}, duration(row.seconds_there)),
      h("td", { class: row.idle ? "alert" : "" }, `${duration(row.idle_seconds)} ago${row.idle ? " (idle)" : ""}`),
      h("td", { class: row.failed_checks ? "alert" : "" }, String(row.failed_checks)),
      h("td", {}, row.session_id === null ? "" : h("a", { href: `/dashboard/live/participants/${row.participant_id}`, "data-action": "watch" }, `Watch participant ${row.participant_id}`))));
  $("#people tbody").replaceChildren(...(rows.length ? rows : [h("tr", {}, h("td", { colspan: 6, class: "muted" }, "Nobody is in the study now."))]));
  const u = snapshot.updates, q = snapshot.queue;
  const item = (key, label, value, alert = false) => h("div", { "data-queue": key }, h("dt", {}, label), h("dd", { class: alert ? "alert" : "" }, value));
  $("#updates").replaceChildren(
    item("pending", "Learner updates pending", String(u.pending)),
    item("sessions", "Agents with updates pending", String(u.sessions_pending)),
    item("oldest", "The oldest pending update queued", u.oldest_wait_seconds === null ? "none pending" : `${duration(u.oldest_wait_seconds)} ago`, (u.oldest_wait_seconds ?? 0) > 10),
    q ? item("running", "Agents updating now", String(q.sessions_updating)) : null,
    q ? item("awaited", "Agents a participant waits for", String(q.sessions_awaited), q.sessions_awaited > 0) : null,
    q ? item("done", "Updates done since the server started", String(q.updates_done)) : null);
}

function showCurves(data) {
  $("#curves-at").textContent = `as of ${formatTime(new Date())}`;
  const box = $("#curves");
  if (!data.environments.length) {
    box.replaceChildren(h("p", { class: "muted" }, "No agent has been evaluated yet."));
    return;
  }
  const thresholds = data.thresholds.map((t) => `${Math.round(t * 100)}%`).join(" / ");
  box.replaceChildren(...data.environments.map((env) => {
    const series = env.learners.map((curve) => {
      const info = learners[curve.learner] ?? { colour: "#555555", display: curve.learner };
      const past = data.thresholds.map((t) => `${Math.round(100 * curve.past[String(t)])}%`).join(" / ");
      return {
        label: info.display,
        colour: info.colour,
        xs: env.episodes,
        ys: curve.mean,
        lows: curve.mean.map((m, i) => (m === null || curve.se[i] === null ? null : m - curve.se[i])),
        highs: curve.mean.map((m, i) => (m === null || curve.se[i] === null ? null : m + curve.se[i])),
        text: `${info.display}: ${curve.sessions} session${curve.sessions === 1 ? "" : "s"}, latest mean ${curve.mean[curve.mean.length - 1]?.toFixed(2) ?? "–"}; past ${thresholds}: ${past}`,
      };
    });
    const title = environmentTitle(env.environment);
    return h("figure", { "data-environment": env.environment },
      h("figcaption", {}, title),
      stepChart({ series, thresholds: data.thresholds, label: `${title}: mean normalised return against episodes, ${series.map((s) => s.text).join("; ")}` }),
      legend(series));
  }));
}

function follow(path, event, show) {
  const source = new EventSource(`${API}/${path}/stream`);
  source.addEventListener(event, (message) => show(JSON.parse(message.data)));
  source.addEventListener("error", () => {
    const stamp = $("#funnel-at");
    if (event === "funnel" && source.readyState !== EventSource.OPEN) {
      stamp.dataset.live = "lost";
      stamp.textContent = "connection lost; reconnecting…";
    }
  });
  window.addEventListener("pagehide", () => source.close());
}

follow("funnel", "funnel", showFunnel);
follow("curves", "curves", showCurves);
