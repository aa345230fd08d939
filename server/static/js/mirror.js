// The one-way mirror: a participant's current session as they see it (the grid, the task, the
// agent, its latest try and each +/-, its learning curve), pushed by the server at each change
// as server-sent events. Read only: this page sends nothing that reaches the participant, and
// it shows no identifier. It follows the participant from agent to agent.

import { environmentTitle, formatTime, h } from "./dom.js";
import { GridView, decodeState, svg } from "./grid.js";
import { stepChart } from "./charts.js";

const main = document.getElementById("mirror");
const participantId = main.dataset.participant;
const $ = (selector) => document.querySelector(selector);
const board = $("#mirror-board");
let grid = null;
let drawn = null; // which session the grid draws: "kind agent environment"
let trail = null;

const STATUS_TEXT = {
  waiting: "Waiting for a place",
  arrived: "At the consent page (or the device check)",
  incompatible: "Turned away by the device check",
  consented: "Reading the instructions",
  declined: "Declined consent",
  questionnaire: "Answering the questionnaire",
  completed: "Done: completed the study",
  submitted: "Done: submitted",
  returned: "Returned the task",
  abandoned: "Abandoned (idle too long)",
};

function stage(view) {
  if (view.check) return `Attention check ${view.check.number} of ${view.check.of}: ${view.check.moves_made} of ${view.check.moves_allowed} moves made`;
  const s = view.session;
  if (s) {
    const what = s.kind === "tutorial" ? "The tutorial" : `Teaching agent ${s.agent} of ${s.of}`;
    const waiting = s.teaching.mode === "agent" && s.teaching.learning.pending > 0 ? ", waiting for the agent's update" : "";
    return `${what}: ${environmentTitle(s.environment.name)}, the ${s.colour.name} agent (${s.learner})${waiting}`;
  }
  return STATUS_TEXT[view.status] ?? view.status;
}

function drawCheck(check) {
  drawn = null;
  grid = null;
  const C = 40;
  const root = svg("svg", { viewBox: `0 0 ${check.size * C} ${check.size * C}`, class: "grid", role: "img", "aria-label": `Attention check grid, ${check.size} by ${check.size}` });
  for (let r = 0; r < check.size; r++) {
    for (let c = 0; c < check.size; c++) {
      svg("rect", { x: c * C, y: r * C, width: C, height: C, fill: "#f7f5ef", stroke: "#c9c3b3" }, root);
    }
  }
  const [sr, sc] = check.star;
  svg("text", { x: sc * C + C / 2, y: sr * C + C * 0.7, "text-anchor": "middle", "font-size": 28, "data-check": "star" }, root).textContent = "\u2605";
  const [rr, rc] = check.robot;
  svg("circle", { cx: rc * C + C / 2, cy: rr * C + C / 2, r: C * 0.35, fill: "#1f2328", "data-check": "robot", "data-row": rr, "data-column": rc }, root);
  board.replaceChildren(h("div", { class: "grid-box" }, root));
}

function drawSession(s) {
  const key = `${s.kind} ${s.agent} ${s.environment.name}`;
  if (key !== drawn) {
    const box = h("div", { class: "grid-box" });
    board.replaceChildren(box);
    grid = new GridView(box, s.environment, { reveal: true, label: `What the participant sees: ${environmentTitle(s.environment.name)}` });
    drawn = key;
    trail = svg("polyline", { class: "try-trail", points: "" }, grid.root);
  }
  const env = s.environment;
  grid.setTask(s.teaching.task);
  grid.setAgent(s.teaching.agent, s.colour.hex);
  board.dataset.state = s.teaching.agent ? s.teaching.agent.state : "";
  board.dataset.mode = s.teaching.mode;
  board.dataset.task = s.teaching.task;
  board.dataset.agent = s.agent ?? "tutorial";
  const cell = grid.root.viewBox.baseVal.width / env.width;
  const states = s.latest_try.length ? [s.latest_try[0].state, ...s.latest_try.map((step) => step.next)] : [];
  trail.setAttribute("points", states.map((state) => {
    const at = decodeState(env, state);
    return `${(at.column + 0.5) * cell},${(at.row + 0.5) * cell}`;
  }).join(" "));
}

function showFacts(s) {
  const t = s.teaching;
  const task = s.environment.tasks[t.task]?.name ?? String(t.task);
  const item = (key, label, value) => h("div", { "data-fact": key }, h("dt", {}, label), h("dd", {}, value));
  $("#mirror-facts").replaceChildren(
    item("task", "Task", task),
    item("mode", "Mode", { idle: "moving the agent (idle)", demonstrate: "demonstrating", agent: "the agent is trying" }[t.mode] ?? t.mode),
    item("episodes", "Episodes ended", String(t.episodes)),
    item("demonstrated", "Demonstrated moves per task", t.demonstrated.join(" · ")),
    item("feedback", "Feedback given", `+${s.feedback_given.good} / −${s.feedback_given.bad}`),
    item("updates", "Learner updates", `${Math.max(0, t.learning.updates)} done, ${t.learning.pending} pending`));
  const marks = s.try_feedback.map((f) => h("span", { class: `feedback-mark ${f.feedback > 0 ? "good" : "bad"}` }, f.feedback > 0 ? "+" : "−"));
  $("#mirror-try").replaceChildren(...(s.latest_try.length
    ? [`${s.latest_try.length} step${s.latest_try.length === 1 ? "" : "s"}: ${s.latest_try.map((x) => x.action).join(", ")}. Feedback on it: `, ...(marks.length ? marks : ["none yet"])]
    : ["The agent has not tried yet."]));
  $("#try-heading").hidden = false;
  const points = s.curve.filter((p) => p.normalized_return !== null);
  $("#mirror-curve").replaceChildren(points.length
    ? stepChart({
      series: [{ label: s.learner, colour: s.colour.hex === "#000000" ? "#1f2328" : s.colour.hex, xs: points.map((p) => p.episodes), ys: points.map((p) => p.normalized_return) }],
      label: `Normalised return after each update: ${points.map((p) => `${p.episodes} episodes ${p.normalized_return.toFixed(2)}`).join(", ")}`,
    })
    : h("p", { class: "muted" }, "Not evaluated yet."));
  $("#mirror-curve").dataset.points = points.length;
  $("#mirror-recent").replaceChildren(...s.recent.map((e) =>
    h("li", {}, `${formatTime(e.at).slice(11)} ${e.kind.replace("_", " ")}`,
      e.action ? ` ${e.action}` : "", e.feedback ? ` ${e.feedback > 0 ? "+ good" : "− bad"}` : "",
      e.episode_end ? ` (episode ends: ${e.episode_end})` : "")));
}

function show(view) {
  const stamp = $("#mirror-at");
  stamp.dataset.live = "on";
  stamp.textContent = `as of ${formatTime(new Date())}`;
  $("#mirror-stage").textContent = stage(view);
  main.dataset.status = view.status;
  const panel = document.querySelector(".mirror-panel");
  if (view.check) {
    drawCheck(view.check);
    panel.hidden = true;
  } else if (view.session) {
    drawSession(view.session);
    showFacts(view.session);
    panel.hidden = false;
  } else {
    drawn = null;
    grid = null;
    board.replaceChildren(h("p", { class: "muted" }, "No agent is being taught now."));
    panel.hidden = true;
  }
}

const source = new EventSource(`/api/admin/live/participants/${participantId}/mirror/stream`);
source.addEventListener("mirror", (message) => show(JSON.parse(message.data)));
source.addEventListener("error", () => {
  if (source.readyState !== EventSource.OPEN) {
    const stamp = $("#mirror-at");
    stamp.dataset.live = "lost";
    stamp.textContent = "connection lost; reconnecting…";
  }
});
window.addEventListener("pagehide", () => source.close());
