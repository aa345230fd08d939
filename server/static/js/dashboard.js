// The experimenter's dashboard: participants, each learning session's curve of normalised
// return against episodes, the replica's MTurk submissions, and a replay of any session's
// recorded events on the participants' grid drawing.

import { ApiError, getJSON, postJSON } from "./api.js";
import { environmentTitle, formatTime, h } from "./dom.js";
import { GridView, decodeState, svg } from "./grid.js";

const API = "/api/admin";
const REFRESH_MS = 10000;
const ACTIONS = ["STAY", "UP", "DOWN", "LEFT", "RIGHT"];
const $ = (selector) => document.querySelector(selector);
let selected = null;
let replayTimer = null;

const time = formatTime;

/** "1 episode", "2 episodes" */
function count(n, noun) {
  return `${n} ${noun}${n === 1 ? "" : "s"}`;
}

function badge(status) {
  return h("span", { class: `badge ${status}` }, status);
}

/** What Prolific's side says beside our status: its status, a return it asked for and not yet
 * made, and when it approves (and pays) the submission by itself, with a warning when close. */
function platformBadges(p) {
  if (!p.prolific_status) return null;
  const asked = p.return_requested_at && p.prolific_status === "AWAITING REVIEW";
  return [
    " ", h("span", { class: "badge", "data-prolific-status": p.prolific_status, title: "Prolific's status" }, `Prolific: ${p.prolific_status}`),
    asked ? [" ", h("span", { class: "badge return-requested", "data-return-requested": p.return_requested_at,
      title: `Prolific asked for a return at ${time(p.return_requested_at)}` }, "asked to return; not returned yet")] : null,
    p.auto_approval_at ? [" ", h("span", { class: `badge ${p.auto_approval_soon ? "auto-approval-soon" : ""}`,
      "data-auto-approval": p.auto_approval_at, "data-soon": String(p.auto_approval_soon) },
      `${p.auto_approval_soon ? "⚠ " : ""}auto-approved ${time(p.auto_approval_at)}`)] : null,
  ];
}

/** The auto-approval date in words, for the participant's review. */
function autoApprovalLine(p) {
  if (!p.auto_approval_at) return null;
  const when = time(p.auto_approval_at);
  return h("p", { class: `auto-approval ${p.auto_approval_soon ? "soon" : ""}`, "data-auto-approval": p.auto_approval_at, role: p.auto_approval_soon ? "alert" : null },
    p.auto_approval_soon
      ? `Prolific approves and pays this submission by itself at ${when}, in less than a week: approve or reject it before then.`
      : `Prolific approves and pays this submission by itself at ${when} unless it is reviewed first.`);
}

async function loadParticipants() {
  const participants = await getJSON(`${API}/participants`);
  const body = $("#participants tbody");
  body.replaceChildren(...participants.map((p) => {
    const row = h("tr", { class: `clickable ${p.participant_id === selected ? "selected" : ""}`, tabindex: 0, "data-participant": p.participant_id, "data-status": p.status },
      h("td", {}, p.participant_id),
      h("td", {}, p.platform),
      h("td", { class: "mono" }, p.platform_participant_id ?? ""),
      h("td", { class: "mono" }, p.platform_submission_id ?? ""),
      h("td", {}, badge(p.status), p.excluded ? [" ", badge("excluded")] : null, platformBadges(p)),
      h("td", {}, p.domain ?? ""),
      h("td", {}, `${p.agents_finished} / ${p.agents}`),
      h("td", {}, p.minutes.toFixed(1)),
      h("td", { class: "mono" }, p.completion_code ?? ""));
    const open = () => showParticipant(p.participant_id, { reveal: true });
    row.addEventListener("click", open);
    row.addEventListener("keydown", (event) => event.key === "Enter" && open());
    return row;
  }));
  // Statuses and domains in rows of their own: a participant is counted once in each.
  const statuses = {};
  const domains = {};
  for (const p of participants) {
    statuses[p.status] = (statuses[p.status] ?? 0) + 1;
    if (p.domain) domains[p.domain] = (domains[p.domain] ?? 0) + 1;
  }
  const row = (group, label, counts, badges) => h("div", { class: "summary-row", "data-group": group, role: "group", "aria-label": label },
    h("span", { class: "summary-label" }, label),
    Object.keys(counts).length
      ? Object.entries(counts).map(([name, n]) => h("span", { class: `badge ${badges ? name : ""}`, "data-name": name }, `${name}: ${n}`))
      : h("span", { class: "muted" }, "none yet"));
  $("#summary").replaceChildren(
    h("p", { class: "summary-total" }, h("span", { class: "badge" }, count(participants.length, "participant"))),
    row("status", "By status", statuses, true),
    row("domain", "By domain", domains, false));
  $("#refreshed").textContent = `updated ${formatTime(new Date())}`;
}

async function loadSubmissions() {
  if (!$("#mturk-submissions")) return; // the MTurk replica is shown for an MTurk study only
  const { submissions } = await getJSON(`${API}/mturk-replica`);
  $("#mturk-submissions tbody").replaceChildren(...(submissions.length
    ? submissions.map((x) => h("tr", { "data-assignment": x.assignment_id },
        h("td", {}, time(x.submitted_at)),
        h("td", { class: "mono" }, x.assignment_id),
        h("td", { class: "mono" }, x.worker_id),
        h("td", {}, h("ul", { class: "fields" }, Object.entries(x.fields).map(([k, v]) => h("li", { class: "mono field" }, `${k} = ${v}`))))))
    : [h("tr", {}, h("td", { colspan: 4, class: "muted" }, "Nothing submitted to the replica yet."))]));
}

/** Fill the detail panel with participant ``id``; with ``reveal`` (the experimenter opened them),
 * scroll the panel into view and move the focus to its heading: it sits below the table, often
 * out of sight, and a keyboard user would otherwise stay on the row. A refresh after a decision
 * leaves the page where it is. */
async function showParticipant(id, { reveal = false } = {}) {
  selected = id;
  for (const row of document.querySelectorAll("#participants tr[data-participant]")) {
    row.classList.toggle("selected", Number(row.dataset.participant) === id);
  }
  const p = await getJSON(`${API}/participants/${id}`);
  const detail = $("#detail");
  const sessions = h("div", { class: "sessions" });
  detail.replaceChildren(
    h("div", { class: "card-head" }, h("h2", { id: "detail-heading", tabindex: -1 }, `Participant ${p.participant_id}`), badge(p.status)),
    h("div", { class: "detail-grid" },
      h("div", {},
        h("p", {}, h("strong", {}, "Worker "), h("span", { class: "mono" }, p.platform_participant_id ?? "(none)")),
        h("p", {}, h("strong", {}, "Assignment "), h("span", { class: "mono" }, p.platform_submission_id ?? "(none)")),
        h("p", {}, h("strong", {}, "Domain "), p.domain ?? "(not yet)", h("strong", {}, "  Time "), `${p.minutes.toFixed(1)} min`),
        h("p", {}, h("a", { href: `/dashboard/live/participants/${p.participant_id}`, "data-action": "watch-live" }, "Watch this participant live (read only)")),
        exclusionForm(p),
        reviewSection(p),
        qualitySection(p),
        erasureSection(p),
        h("h3", {}, "Status history"),
        h("ol", { class: "history" }, p.status_changes.map((c) => h("li", {}, badge(c.status), " ", time(c.at), c.note ? ` (${c.note})` : "")))),
      sessions));
  detail.hidden = false;
  if (reveal) {
    const still = window.matchMedia("(prefers-reduced-motion: reduce)").matches;
    $("#detail-heading").focus({ preventScroll: true });
    detail.scrollIntoView({ behavior: still ? "auto" : "smooth", block: "start" });
  }
  for (const session of p.sessions) {
    const card = h("div", { class: "session-card", "data-session": session.session_id },
      h("h3", {}, h("span", { class: "colour-dot", title: session.colour, style: `background: ${session.colour_hex}` }),
        session.kind === "tutorial" ? "Tutorial" : `Agent ${session.position + 1} · ${environmentTitle(session.environment)}`),
      h("p", {}, `${session.learner} · ${session.colour} · `, badge(session.status)),
      h("p", { class: "muted" }, `${count(session.episodes, "episode")}, ${count(session.actions, "action")}`,
        session.final_normalized_return !== null ? `, return ${(100 * session.final_normalized_return).toFixed(0)}%` : ""),
      h("div", { class: "curve-box" }, h("p", { class: "muted" }, "Loading the curve…")),
      h("button", { class: "btn quiet", type: "button", "data-action": "replay", onclick: () => showReplay(session.session_id) }, "Replay"));
    sessions.appendChild(card);
    getJSON(`${API}/sessions/${session.session_id}/evaluations`).then((evaluations) => {
      card.querySelector(".curve-box").replaceChildren(curve(evaluations));
    });
  }
}

/** Exclude the participant from analysis, or include them again, with the reason. */
function exclusionForm(p) {
  const reason = h("input", { type: "text", id: "exclusion-reason", name: "reason", maxlength: 2000,
    placeholder: p.excluded ? "Why include them again" : "Why exclude them (kept with the data)" });
  const message = h("p", { class: "form-error", role: "alert", hidden: true });
  const button = h("button", { class: "btn", type: "submit", "data-action": p.excluded ? "include" : "exclude" },
    p.excluded ? "Include again" : "Exclude from analysis");
  const form = h("form", { class: "exclusion" },
    p.excluded
      ? h("p", {}, h("strong", {}, "Excluded: "), p.exclusion_reason ?? "")
      : h("p", { class: "muted" }, "Included in the analysis."),
    h("label", { for: "exclusion-reason" }, "Reason"), reason, button, message);
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    if (!reason.value.trim()) {
      message.hidden = false;
      message.textContent = "Give a reason: it is kept with the data.";
      return;
    }
    button.disabled = true;
    const what = p.excluded ? "inclusion" : "exclusion";
    try {
      await postJSON(`${API}/participants/${p.participant_id}/${what}`, { reason: reason.value.trim() });
      await Promise.all([loadParticipants(), showParticipant(p.participant_id)]);
    } catch (error) {
      message.hidden = false;
      message.textContent = error instanceof ApiError ? error.detail : "The server could not be reached.";
      button.disabled = false;
    }
  });
  return form;
}

/** The quality checks of a participant who completed (quality.csv), loaded after the rest. */
function qualitySection(p) {
  const none = () => h("p", { class: "muted" }, "No quality checks until the participant completes.");
  const completed = p.status === "completed" || p.status === "submitted";
  const body = h("div", {}, completed ? h("p", { class: "muted" }, "Loading the quality checks…") : none());
  if (completed) getJSON(`${API}/participants/${p.participant_id}/quality`).then((q) => {
    const share = (x) => (x === null ? "not judged" : `${Math.round(100 * x)}%`);
    body.replaceChildren(
      h("ul", { class: "quality" },
        h("li", {}, `Time: ${q.minutes.toFixed(1)} min`, q.minutes_z === null ? "" : ` (${q.minutes_z} s.d. from the others)`),
        h("li", {}, `Longest idle stretch: ${q.longest_idle_minutes.toFixed(1)} min`),
        h("li", {}, `Optimal demonstrated moves: ${share(q.optimal_demonstration_share)}`),
        h("li", {}, `Consistent feedback: ${share(q.consistent_feedback_share)}`),
        h("li", { "data-quality": "attention-checks" }, q.attention_checks === 0
          ? "Attention checks: none taken"
          : `Attention checks failed: ${q.failed_attention_checks} of ${q.attention_checks}`)),
      h("p", {}, h("strong", {}, "Flags: "), q.flags || "none",
        h("strong", {}, "  Prolific ground: "), q.prolific_ground === "none" ? "none applies" : q.prolific_ground));
  }).catch(() => body.replaceChildren(none()));
  return h("section", { class: "quality-checks", "aria-labelledby": "quality-heading" },
    h("h3", { id: "quality-heading" }, "Quality checks"), body);
}

/** Erase the participant on their request, after a confirmation: nothing of theirs is left
 * but the audit row (erasures.csv). */
function erasureSection(p) {
  const message = h("p", { class: "form-error", role: "alert", hidden: true });
  const button = h("button", { class: "btn danger", type: "button", "data-action": "erase" }, "Erase this participant's data");
  button.addEventListener("click", async () => {
    const who = p.platform_participant_id ? `worker ${p.platform_participant_id}` : `participant ${p.participant_id}`;
    if (!window.confirm(`Erase every record of ${who}? Their events, agents, answers and payments records are deleted for good; only an audit row with their pseudonym is kept.`)) return;
    button.disabled = true;
    try {
      await postJSON(`${API}/participants/${p.participant_id}/erasure`, {});
      selected = null;
      $("#detail").replaceChildren(h("p", { role: "status" }, `Participant ${p.participant_id} was erased.`));
      await loadParticipants();
    } catch (error) {
      message.hidden = false;
      message.textContent = error instanceof ApiError ? error.detail : "The server could not be reached.";
      button.disabled = false;
    }
  });
  return h("section", { class: "erasure", "aria-labelledby": "erasure-heading" },
    h("h3", { id: "erasure-heading" }, "Withdrawal"),
    h("p", { class: "muted" }, "On the participant's request: deletes all their data."),
    button, message);
}

/** A request token for a bonus (MTurk's UniqueRequestToken), made when its form is drawn: a
 * retry of the same form sends the same token and pays nothing more. */
function requestToken() {
  const bytes = crypto.getRandomValues(new Uint8Array(16));
  return Array.from(bytes, (b) => b.toString(16).padStart(2, "0")).join("");
}

/** Why the quality checks suggest a Prolific ground, in words. */
function groundReason(q) {
  if (q.prolific_ground === "FAILED_CHECK") {
    return `${q.failed_attention_checks} of ${q.attention_checks} attention checks failed`;
  }
  if (q.prolific_ground === "TOO_QUICKLY") return `exceptionally fast: ${q.minutes_z} s.d. below the others' mean`;
  return q.flags;
}

const REJECTION_CATEGORIES = ["TOO_QUICKLY", "TOO_SLOWLY", "FAILED_INSTRUCTIONS", "INCOMP_LONGITUDINAL",
  "FAILED_CHECK", "LOW_EFFORT", "MALINGERING", "NO_CODE", "BAD_CODE", "NO_DATA", "UNSUPP_DEVICE", "OTHER"];

/** Approve or reject the participant's submitted work (an MTurk assignment or a Prolific
 * submission), and pay bonuses (sent to the review backend: the platform or its replica). */
function reviewSection(p) {
  const heading = h("h3", { id: "review-heading" }, "Review of the submission");
  if (p.platform !== "mturk" && p.platform !== "prolific") {
    return h("section", { class: "review", "aria-labelledby": "review-heading" }, heading,
      h("p", { class: "muted" }, `Approvals and bonuses are for MTurk and Prolific participants; this participant came from ${p.platform}.`));
  }
  const prolific = p.platform === "prolific";
  const returnAsked = p.return_requested_at
    ? h("p", { "data-return-requested": p.return_requested_at },
      p.prolific_status === "RETURNED"
        ? `Prolific asked them to return the submission at ${time(p.return_requested_at)}, and they did.`
        : `Asked to return; not returned yet: Prolific asked at ${time(p.return_requested_at)}. Until they return it, it awaits review like any other.`)
    : null;
  if (!p.awaits_decision && !p.review) {
    return h("section", { class: "review", "aria-labelledby": "review-heading" }, heading, returnAsked,
      h("p", { class: "muted" }, p.status === "submitted"
        ? `Prolific shows this submission as ${p.prolific_status}: it is not open to review.`
        : "The review opens once the participant has submitted their work."));
  }
  // Each form says what is wrong under its own buttons: the decision's, the bonus's.
  const errorLine = (id) => h("p", { class: "form-error", id, role: "alert", hidden: true });
  const complain = (message, text) => {
    message.hidden = false;
    message.textContent = text;
  };
  const send = async (what, body, buttons, message) => {
    buttons.forEach((b) => { b.disabled = true; });
    message.hidden = true;
    try {
      await postJSON(`${API}/participants/${p.participant_id}/${what}`, body);
      await Promise.all([loadParticipants(), showParticipant(p.participant_id)]);
    } catch (error) {
      complain(message, error instanceof ApiError ? error.detail : "The server could not be reached.");
      buttons.forEach((b) => { b.disabled = false; });
    }
  };
  let decision;
  if (p.review) {
    decision = h("p", { "data-review": p.review.decision }, badge(p.review.decision), " ",
      p.review.state === "done" ? time(p.review.decided_at) : "not yet confirmed by the platform: send it again",
      p.review.rejection_category ? ` ${p.review.rejection_category}` : "",
      p.review.message ? ` (${p.review.message})` : "");
  } else {
    const message = errorLine("review-error");
    const feedback = h("textarea", { id: "review-feedback", name: "feedback", rows: 2, maxlength: 1024, "aria-describedby": message.id });
    const approve = h("button", { class: "btn", type: "button", "data-action": "approve" }, "Approve");
    const reject = h("button", { class: "btn", type: "button", "data-action": "reject" }, "Reject");
    const category = h("select", { id: "review-category", name: "rejection_category" },
      h("option", { value: "" }, "(rejection category)"), ...REJECTION_CATEGORIES.map((c) => h("option", { value: c }, c)));
    feedback.addEventListener("input", () => {
      feedback.removeAttribute("aria-invalid");
      message.hidden = true;
    });
    approve.addEventListener("click", () => {
      if (!window.confirm("Approve this submission? A decision is final.")) return;
      send("approval", { message: prolific ? null : feedback.value.trim() || null }, [approve, reject], message);
    });
    reject.addEventListener("click", () => {
      const text = feedback.value.trim();
      const problem = !text ? "A rejection needs feedback: the participant is shown why."
        : prolific && text.length < 100 ? "Prolific needs a rejection message of at least 100 characters."
        : prolific && !category.value ? "Prolific needs a rejection category." : null;
      if (problem) {
        complain(message, problem);
        feedback.setAttribute("aria-invalid", "true");
        feedback.focus();
        return;
      }
      // As Approve and Pay: a decision is final, so it is asked first.
      if (!window.confirm("Reject this submission? A decision is final: the participant is not paid for it.")) return;
      send("rejection", { message: text, rejection_category: prolific ? category.value : null }, [approve, reject], message);
    });
    const checked = p.status === "completed" || p.status === "submitted";
    const suggestion = h("p", { class: "muted", "data-testid": "suggested-ground" }, checked
      ? "Suggested ground: loading the quality checks…"
      : "Suggested ground: none (no quality checks: they did not do the study).");
    if (checked) getJSON(`${API}/participants/${p.participant_id}/quality`).then((q) => {
      suggestion.textContent = q.prolific_ground === "none"
        ? "Suggested ground: none (the quality checks support no rejection)."
        : `Suggested ground: ${q.prolific_ground} (${groundReason(q)}).`;
      if (q.prolific_ground === "none") return;
      suggestion.classList.remove("muted");
      if (prolific && !category.value) category.value = q.prolific_ground;
    }).catch(() => { suggestion.textContent = "Suggested ground: the quality checks are not available."; });
    decision = h("div", { class: "review-decision" },
      h("p", { class: "muted" }, "Not reviewed yet."),
      suggestion,
      h("label", { for: "review-feedback" }, prolific ? "Rejection message (at least 100 characters)" : "Feedback to the worker (needed to reject)"), feedback,
      ...(prolific ? [h("label", { for: "review-category" }, "Rejection category"), category] : []),
      h("div", { class: "review-buttons" }, approve, reject), message);
  }
  const bonusMessage = errorLine("bonus-error");
  const amount = h("input", { id: "bonus-amount", name: "amount", type: "number", min: "0.01", step: "0.01", inputmode: "decimal", required: true });
  const reason = h("input", { id: "bonus-reason", name: "reason", type: "text", maxlength: 1024, required: true });
  const pay = h("button", { class: "btn", type: "submit", "data-action": "bonus" }, "Pay the bonus");
  const token = requestToken();
  const bonusForm = h("form", { class: "bonus" },
    h("label", { for: "bonus-amount" }, prolific ? "Bonus (the study's currency)" : "Bonus (USD)"), amount,
    h("label", { for: "bonus-reason" }, "Reason, shown to the participant"), reason, pay, bonusMessage);
  bonusForm.addEventListener("submit", (event) => {
    event.preventDefault();
    if (!amount.value || !reason.value.trim()) {
      complain(bonusMessage, "A bonus needs an amount and a reason.");
      return;
    }
    if (!window.confirm(`Pay a bonus of ${amount.value}? It is paid once, with this form's request token.`)) return;
    send("bonuses", { amount: amount.value, reason: reason.value.trim(), unique_token: token }, [pay], bonusMessage);
  });
  // An unsettled bonus is sent again with its own token: the server settles it (a Prolific
  // bonus in doubt from Prolific's record of the submission's bonuses) and never pays twice.
  const bonusItem = (b) => {
    const label = b.state === "paid" ? time(b.paid_at)
      : b.state === "in_doubt" ? "in doubt: neither paid nor unpaid until settled"
      : `${b.state}: not yet confirmed paid`;
    const item = h("li", { "data-amount": b.amount, "data-state": b.state },
      `${b.amount} ${b.currency} · ${b.reason} · ${label}`);
    if (b.state === "paid") return item;
    const settleMessage = errorLine(`bonus-settle-${b.unique_token}`);
    const settle = h("button", { class: "btn", type: "button", "data-action": "settle-bonus" }, "Settle it");
    settle.addEventListener("click", () => {
      send("bonuses", { amount: b.amount, reason: b.reason, unique_token: b.unique_token }, [settle], settleMessage);
    });
    item.append(h("p", { class: "muted bonus-note" }, b.note || ""), settle, settleMessage);
    return item;
  };
  const why = p.status === "declined"
    ? h("p", { class: "muted" }, "They declined consent; Prolific completed their submission with the NO_CONSENT code, so it is paid unless it is returned or rejected.")
    : p.prolific_status === "TIMED-OUT"
      ? h("p", { class: "muted" }, "They finished although Prolific timed their submission out; Prolific lets a timed-out submission be approved.")
      : null;
  if (p.status !== "submitted") {
    // Bonuses are for submitted work only.
    return h("section", { class: "review", "aria-labelledby": "review-heading" }, heading, why, returnAsked, autoApprovalLine(p), decision);
  }
  return h("section", { class: "review", "aria-labelledby": "review-heading" }, heading, why, returnAsked, autoApprovalLine(p), decision,
    h("h4", {}, "Bonuses"),
    p.bonuses.length
      ? h("ul", { class: "bonuses" }, p.bonuses.map(bonusItem))
      : h("p", { class: "muted" }, "No bonus paid."),
    bonusForm);
}

/** Normalised return (0..1) after each update, against the episodes so far. */
function curve(evaluations) {
  const done = evaluations.filter((e) => e.status === "done" && e.normalized_return !== null);
  if (!done.some((e) => e.episodes > 0)) {
    return h("p", { class: "muted no-curve" }, "No episode yet: the curve starts with the first one.");
  }
  const W = 260, H = 130, L = 36, R = 8, T = 8, B = 22;
  const root = svg("svg", { viewBox: `0 0 ${W} ${H}`, class: "curve", role: "img", "data-points": done.length,
    "aria-label": `Normalised return after ${done.length} updates` });
  const maxEpisodes = Math.max(1, ...done.map((e) => e.episodes));
  const x = (episodes) => L + ((W - L - R) * episodes) / maxEpisodes;
  const y = (value) => T + (H - T - B) * (1 - Math.max(0, Math.min(1, value)));
  svg("line", { x1: L, y1: y(0), x2: W - R, y2: y(0), class: "axis" }, root);
  svg("line", { x1: L, y1: y(0), x2: L, y2: y(1), class: "axis" }, root);
  for (const level of [0.5, 0.8, 1]) {
    svg("line", { x1: L, y1: y(level), x2: W - R, y2: y(level), class: "ref" }, root);
    svg("text", { x: L - 4, y: y(level) + 3, "text-anchor": "end" }, root).textContent = `${level * 100}%`;
  }
  svg("text", { x: L - 4, y: y(0) + 3, "text-anchor": "end" }, root).textContent = "0";
  svg("text", { x: (L + W - R) / 2, y: H - 4, "text-anchor": "middle" }, root).textContent = `episodes (0 to ${maxEpisodes})`;
  if (done.length) {
    svg("path", { d: done.map((e, i) => `${i ? "L" : "M"}${x(e.episodes).toFixed(1)} ${y(e.normalized_return).toFixed(1)}`).join(" "), class: "line" }, root);
    for (const e of done) {
      const point = svg("circle", { cx: x(e.episodes), cy: y(e.normalized_return), r: 3.5, class: "point" }, root);
      svg("title", {}, point).textContent = `update ${e.update_index}: ${e.episodes} episodes, ${e.actions} actions, ${(100 * e.normalized_return).toFixed(1)}%`;
    }
  }
  return root;
}

// -- replay -----------------------------------------------------------------------------------
function describe(event, env) {
  const task = event.task !== null ? env.tasks[event.task]?.name : null;
  const action = event.action !== null ? ACTIONS[event.action] : null;
  const parts = [event.kind.replace("_", " ")];
  if (event.kind === "mode") parts.push(`→ ${event.mode}`);
  if (event.kind === "task") parts.push(`→ ${task}`);
  if ((event.kind === "mode" || event.kind === "task") && event.next_state !== event.state) parts.push("(was on the goal: to a random start)");
  if (action) parts.push(action);
  if (event.record === "demonstration") parts.push(`(demonstration of ${task})`);
  if (event.record === "transition") parts.push("(idle move)");
  if (event.kind === "feedback") parts.push(event.feedback > 0 ? "+ good" : "− bad");
  if (event.stay_state !== null) parts.push("+ STAY");
  if (event.episode_end) parts.push(`[episode ${event.episode_index} ends: ${event.episode_end}]`);
  return parts.join(" ");
}

async function showReplay(sessionId) {
  clearInterval(replayTimer);
  const data = await getJSON(`${API}/sessions/${sessionId}/replay`);
  const env = data.environment;
  const box = $("#replay");
  box.hidden = false;
  if (data.start_state === null) {
    box.replaceChildren(h("h2", {}, `Replay of session ${sessionId}`), h("p", { class: "muted" }, "This session has not started."));
    return;
  }
  // One frame per event: where the agent is, which task and mode, after it.
  const frames = [{ state: data.start_state, task: 0, mode: "idle", text: "start" }];
  for (const event of data.events) {
    const last = frames[frames.length - 1];
    frames.push({
      state: event.stay_state ?? event.next_state ?? last.state,
      task: event.task ?? last.task,
      mode: event.episode_end ? "idle" : event.mode ?? last.mode,
      text: `#${event.seq} ${describe(event, env)}`,
    });
  }
  const board = h("div", { class: "grid-box" });
  const frame = h("div", { class: "replay-board" }, board);
  const label = h("p", { class: "replay-event", role: "status" });
  const slider = h("input", { type: "range", min: 0, max: frames.length - 1, value: 0, "aria-label": "Event" });
  const log = h("ol", { start: 0 }, frames.map((f) => h("li", {}, f.text)));
  const play = h("button", { class: "btn", type: "button", "data-action": "play" });
  // Drawn, not a font's glyph: Debian's fonts lack the pause sign.
  const showPlaying = (on) => {
    const icon = svg("svg", { viewBox: "0 0 10 10", class: "play-icon", "aria-hidden": "true", "data-icon": on ? "pause" : "play" });
    if (on) {
      svg("rect", { x: 1.5, y: 1, width: 2.5, height: 8 }, icon);
      svg("rect", { x: 6, y: 1, width: 2.5, height: 8 }, icon);
    } else {
      svg("path", { d: "M2 1 L9 5 L2 9 Z" }, icon);
    }
    play.replaceChildren(icon, on ? " Pause" : " Play");
  };
  showPlaying(false);
  const button = (text, action, go) => h("button", { class: "btn quiet", type: "button", "data-action": action, onclick: go }, text);
  box.replaceChildren(
    h("div", { class: "card-head" }, h("h2", {}, `Replay: session ${sessionId}, ${environmentTitle(env.name)}, ${data.session.learner}`),
      h("span", { class: "muted" }, `${data.events.length} events`)),
    h("div", { class: "replay-layout" },
      h("div", {}, frame,
        h("div", { class: "replay-controls" },
          button("◀◀ First", "first", () => go(0)),
          button("◀ Back", "back", () => go(index - 1)),
          play,
          button("Next ▶", "forward", () => go(index + 1)),
          button("Last ▶▶", "last", () => go(frames.length - 1)),
          slider),
        label),
      h("div", { class: "replay-log", tabindex: 0, role: "region", "aria-label": "Recorded events" }, log)));
  const view = new GridView(board, env, { reveal: true, label: `Replay of session ${sessionId}` });
  const fit = () => {
    const ratio = env.width / env.height;
    const size = Math.min(frame.clientWidth, frame.clientHeight * ratio);
    board.style.width = `${Math.floor(size)}px`;
    board.style.height = `${Math.floor(size / ratio)}px`;
  };
  new ResizeObserver(fit).observe(frame);
  let index = 0;
  const go = (i) => {
    index = Math.max(0, Math.min(frames.length - 1, i));
    const f = frames[index];
    view.setTask(f.task);
    view.setAgent(decodeState(env, f.state), data.session.colour_hex ?? "#888888");
    board.dataset.frame = index;
    board.dataset.state = f.state;
    slider.value = index;
    label.textContent = `Event ${index} of ${frames.length - 1}: ${f.text} · task ${env.tasks[f.task]?.name} · ${f.mode}`;
    log.querySelectorAll("li").forEach((li, k) => li.classList.toggle("current", k === index));
    log.children[index]?.scrollIntoView({ block: "nearest" });
  };
  slider.addEventListener("input", () => go(Number(slider.value)));
  play.addEventListener("click", () => {
    if (replayTimer) {
      clearInterval(replayTimer);
      replayTimer = null;
      showPlaying(false);
      return;
    }
    showPlaying(true);
    replayTimer = setInterval(() => {
      if (index >= frames.length - 1) {
        clearInterval(replayTimer);
        replayTimer = null;
        showPlaying(false);
        return;
      }
      go(index + 1);
    }, 300);
  });
  go(0);
  const still = window.matchMedia("(prefers-reduced-motion: reduce)").matches;
  box.scrollIntoView({ behavior: still ? "auto" : "smooth", block: "start" });
}

function seconds(value) {
  return value < 60 ? `${value.toFixed(1)} s` : `${(value / 60).toFixed(1)} min`;
}

async function loadQueue() {
  const q = await getJSON(`${API}/queue`);
  const item = (key, label, value, note = null, alert = false) =>
    h("div", { "data-queue": key },
      h("dt", {}, label, note ? h("span", { class: "muted" }, ` (${note})`) : null),
      h("dd", { class: alert ? "alert" : "" }, value));
  const capacity = q.capacity === null ? "not measured yet" : String(q.capacity);
  const limit = q.limit === null ? "none" : `${q.participants_active} / ${q.limit}`;
  $("#queue").replaceChildren(
    item("capacity", "Capacity: participants at once without waiting", capacity,
      q.capacity === null ? null : `an update takes ${q.update_seconds.toFixed(2)} s on ${q.measured_on}, ${count(q.slots, "slot")}` +
        (q.server_seconds_per_update === null ? "" : `, the server's own work ${q.server_seconds_per_update.toFixed(2)} s of a core per update`)),
    item("longest", "The longest update",
      q.longest_update_seconds === null ? "not timed yet" : seconds(q.longest_update_seconds),
      q.longest_update_seconds === null ? null : `${q.longest_update_of}: an agent that follows one is ready that long after its episode, however few teach`,
      q.longest_update_seconds !== null && q.longest_update_seconds > 2),
    item("active", "Participants in the study / limit", limit, q.limit_from ? `limit from the ${q.limit_from}` : "no limit"),
    item("waiting", "Participants waiting for a place", String(q.participants_waiting)),
    item("pending", "Learner updates pending", String(q.updates_pending), `${q.sessions_updating} running`),
    item("awaited", "Agents someone waits for", String(q.sessions_awaited)),
    item("oldest-wait", "The oldest wait", seconds(q.oldest_wait_seconds), null, q.oldest_wait_seconds > 2));
}

/** The deployment's servers with their heartbeats and load (one row with one server); servers
 * whose update slots share a machine (or a Dask cluster) have the same machine number. */
async function loadServers() {
  const servers = await getJSON(`${API}/servers`);
  const machines = [...new Set(servers.map((s) => s.machine))];
  $("#servers tbody").replaceChildren(...servers.map((s) =>
    h("tr", { "data-server": s.name, "data-machine": String(machines.indexOf(s.machine) + 1) },
      h("td", {}, s.name, s.this_server ? h("span", { class: "muted" }, " (this page's)") : null),
      h("td", { title: s.machine || "not stated" },
        `${s.host}, machine ${machines.indexOf(s.machine) + 1}`,
        s.cores === null ? " (a cluster's workers)" : ` (${s.cores} cores)`),
      h("td", { class: s.live ? "" : "alert" }, s.live ? "live" : (s.stopped_at ? "stopped" : "gone (no heartbeat)")),
      h("td", {}, time(s.started_at)),
      h("td", {}, time(s.heartbeat_at)),
      h("td", {}, String(s.update_slots)),
      h("td", {}, String(s.updates_running)),
      h("td", {}, String(s.updates_completed)),
      h("td", {}, String(s.updates_failed)),
      h("td", {}, s.participants_at_once === null ? "not timed yet" : String(s.participants_at_once)))));
}

async function refresh() {
  try {
    await Promise.all([loadParticipants(), loadSubmissions(), loadQueue(), loadServers()]);
  } catch (error) {
    $("#refreshed").textContent = `could not update: ${error.message}`;
  }
}

await refresh();
setInterval(refresh, REFRESH_MS);
