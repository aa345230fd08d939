// The participant's page: asks the server where the participant is and shows that step
// (consent, instructions, the tutorial, an agent, an attention check between agents if the
// study has them, the questionnaire if the study has one, completion), so that a reload
// continues there.

import { ApiError, Sequencer, getJSON, postJSON, useParticipantToken } from "./api.js";
import { AttentionCheck } from "./attention.js";
import { deviceCheck } from "./device.js";
import { environmentTitle, h, paragraphs } from "./dom.js";
import { robotIcon, svg } from "./grid.js";
import { Teacher } from "./teach.js";
import { Tutorial } from "./tutorial.js";

const study = JSON.parse(document.getElementById("study-data").textContent);
// A token in the page (a new one, given when this load arrived without a valid cookie).
const tokenData = document.getElementById("participant-token");
if (tokenData) {
  useParticipantToken(JSON.parse(tokenData.textContent));
  tokenData.remove();
}
const app = document.getElementById("app");
let seq = null;
let participant = null;
let teacher = null;
let check = null;
let deviceChecked = false; // this load passed the device check (a reload checks again)
let deviceProblems = null; // what this load's device check found, when it turned the participant away

const offline = h("div", { class: "offline", role: "alert", hidden: true },
  h("span", { class: "spinner", "aria-hidden": "true" }), " The connection to the study server was lost; retrying…");
document.body.appendChild(offline);
const connection = {
  down: () => { offline.hidden = false; },
  up: () => { offline.hidden = true; },
};

// "Stop and delete my data", below every page of the study once the participant is known: one
// confirmation, then every record of theirs is erased and the page says how to leave the
// platform (Prolific: back with the study's NO_CONSENT code, if it has one).
const withdrawButton = h("button", { class: "btn quiet withdraw-open", type: "button", "data-action": "withdraw", "aria-haspopup": "dialog" },
  "Stop and delete my data");
const withdrawConfirm = h("button", { class: "btn danger", type: "button", "data-action": "withdraw-confirm" }, "Delete my data and stop");
const withdrawKeep = h("button", { class: "btn", type: "button", "data-action": "withdraw-keep" }, "Keep going");
const withdrawError = h("p", { class: "form-error", role: "alert", hidden: true });
const withdrawDialog = h("dialog", { class: "withdraw-dialog", "aria-labelledby": "withdraw-title", "aria-describedby": "withdraw-text" },
  h("h2", { id: "withdraw-title" }, "Stop and delete your data?"),
  h("p", { id: "withdraw-text" }, "The study stops here, and everything you did in it is deleted from our records: your answers, your moves and the agents you taught. This cannot be undone. You will not receive a completion code."),
  withdrawError,
  h("div", { class: "actions" }, withdrawKeep, withdrawConfirm));
const withdrawBar = h("footer", { class: "withdraw-bar", hidden: true },
  h("p", {}, "You may leave the study at any time. ", withdrawButton), withdrawDialog);
document.body.appendChild(withdrawBar);
withdrawButton.addEventListener("click", () => {
  withdrawError.hidden = true;
  withdrawConfirm.disabled = false;
  withdrawDialog.showModal();
  withdrawKeep.focus();
});
withdrawKeep.addEventListener("click", () => withdrawDialog.close());
withdrawDialog.addEventListener("close", () => { if (!withdrawBar.hidden) withdrawButton.focus(); });
withdrawConfirm.addEventListener("click", async () => {
  withdrawConfirm.disabled = true;
  let done;
  try {
    done = await postJSON("/api/participant/withdrawal", {});
  } catch (error) {
    withdrawError.hidden = false;
    withdrawError.textContent = error instanceof ApiError ? error.detail : "The study server could not be reached: please try again.";
    withdrawConfirm.disabled = false;
    return;
  }
  withdrawBar.hidden = true;
  withdrawDialog.close();
  // No redirect of its own: the participant reads what happened, then goes back to the platform.
  const back = done.redirect_url
    ? [h("p", {}, h("a", { class: "btn primary big", href: done.redirect_url, target: "_top", "data-action": "leave-platform" }, "Back to Prolific"))]
    : [];
  show(sheet(h("h1", {}, "Your data has been deleted"), h("p", { "data-withdrawn": done.platform }, done.message), ...back));
});

function show(...children) {
  teacher?.close();
  teacher = null;
  check?.close();
  check = null;
  app.replaceChildren(...children);
  const heading = app.querySelector("h1");
  if (heading) {
    heading.setAttribute("tabindex", "-1");
    heading.focus({ preventScroll: true });
  }
  window.scrollTo(0, 0);
}

function sheet(...children) {
  return h("main", { class: "sheet" }, h("img", { class: "sheet-logo", src: "/static/img/robot.svg", alt: "", width: 56, height: 56 }), ...children);
}

/** A sheet whose own picture of a robot stands in for the logo. */
function plainSheet(...children) {
  return h("main", { class: "sheet" }, ...children);
}

function failure(error) {
  if (error instanceof ApiError && error.status === 401) {
    withdrawBar.hidden = true;
    show(sheet(
      h("h1", {}, "Your place in the study could not be found"),
      h("p", {}, "Your browser did not keep the study's cookie. Please open the study again from its link; you will continue where you were."),
      h("button", { class: "btn primary", type: "button", onclick: () => window.location.reload() }, "Reload")));
    return;
  }
  console.warn(error);
  show(sheet(
    h("h1", {}, "Something went wrong"),
    h("p", {}, error instanceof ApiError ? error.detail : "The page could not reach the study server."),
    h("p", {}, "Your progress is saved. Reload the page to continue."),
    h("button", { class: "btn primary", type: "button", onclick: () => window.location.reload() }, "Reload")));
}

async function refresh() {
  participant = await getJSON("/api/participant", { onRetry: connection.down });
  connection.up();
  withdrawBar.hidden = false;
  if (seq) seq.nextSeq = participant.next_seq;
  else seq = new Sequencer(participant.next_seq, connection);
  return participant;
}

async function route() {
  switch (participant.status) {
    case "arrived":
      if (study.device_check && !deviceChecked) return deviceCheckPage();
      return consentPage();
    case "incompatible":
      return incompatiblePage();
    case "declined":
      return declinedPage();
    case "consented":
      return instructionsPage();
    case "questionnaire":
      return questionnairePage();
    case "completed":
    case "submitted":
      return completionPage();
    default:
      if (participant.attention_check) return attentionPage(participant.attention_check);
      if (participant.current_session_id !== null) {
        const current = participant.sessions.find((x) => x.session_id === participant.current_session_id);
        if (current && !current.opened) return meetPage(current);
        return teach(participant.current_session_id);
      }
      return failure(new ApiError(409, `Unexpected status ${participant.status}.`));
  }
}

async function post(url, body = {}) {
  try {
    return await seq.post(url, body);
  } catch (error) {
    if (error instanceof ApiError && error.resync) {
      // Another tab moved the study on: show where it is now.
      await refresh();
      await route();
      return null;
    }
    failure(error);
    return null;
  }
}

// -- the device check, before consent --------------------------------------------------------
async function deviceCheckPage() {
  const needs = study.device_check;
  const page = sheet();
  const report = deviceCheck(page, needs);
  show(page);
  page.classList.add("device-sheet");
  const measured = await report;
  if (await post("/api/participant/device-check", measured)) {
    deviceChecked = true;
    deviceProblems = [];
    if (!measured.arrow_key) deviceProblems.push("no arrow key was pressed");
    if (measured.width < needs.min_width || measured.height < needs.min_height) {
      deviceProblems.push(`your window was ${measured.width} \u00d7 ${measured.height} pixels, smaller than the ${needs.min_width} \u00d7 ${needs.min_height} the study needs`);
    }
    if (measured.missing.length) deviceProblems.push(`your browser lacks what the study uses (${measured.missing.join(", ")})`);
    await refresh();
    route();
  }
}

function incompatiblePage() {
  const back = participant.completion && participant.completion.redirect_url;
  const why = deviceProblems && deviceProblems.length
    ? h("p", { "data-device": "problems" }, `The check found that ${deviceProblems.join("; ")}.`)
    : null;
  show(sheet(
    h("h1", {}, "Sorry: this study cannot run on your device"),
    h("p", { class: "lead" }, "The study is done with the arrow keys of a keyboard, in a large enough browser window, and your device or window did not pass the check."),
    why,
    participant.platform === "mturk"
      ? h("p", {}, "Please return the HIT so that someone else can take it; you may accept it again from a computer with a keyboard.")
      : null,
    back ? [h("p", {}, "You are being sent back to Prolific, which will ask you to return the study. If nothing happens, press the button."),
      h("a", { class: "btn primary big", href: back, target: "_top", "data-action": "return-prolific" }, "Return to Prolific")]
      : participant.platform === "prolific"
        ? h("p", {}, "Please return the study on Prolific, so that you are not counted as having taken part.")
        : participant.platform === "lab"
          ? h("p", {}, "Please tell the experimenter.")
          : null,
    h("p", {}, "Nothing more will be recorded. You may close this page.")));
  if (back) window.open(back, "_top");
}

// -- consent and instructions ---------------------------------------------------------------
function consentPage() {
  const agree = h("button", { class: "btn primary big", type: "button", "data-action": "agree" }, "I agree to take part");
  const decline = h("button", { class: "btn big", type: "button", "data-action": "decline" }, "I do not agree");
  const answer = async (yes) => {
    agree.disabled = decline.disabled = true;
    if (await post("/api/participant/consent", { agree: yes })) {
      await refresh();
      route();
    }
  };
  agree.addEventListener("click", () => answer(true));
  decline.addEventListener("click", () => answer(false));
  // The text scrolls in its own box, which the keyboard can reach (Tab, then the arrow keys),
  // so that the answers stay in view under it.
  show(sheet(
    h("h1", {}, study.title),
    h("p", { class: "lead" }, study.payment),
    h("h2", { id: "consent-heading" }, "Consent to take part"),
    h("div", { class: "consent-text", tabindex: 0, role: "region", "aria-labelledby": "consent-heading" }, paragraphs(study.consent)),
    h("div", { class: "actions" }, agree, decline)));
  app.querySelector(".sheet").classList.add("consent-sheet");
}

function declinedPage() {
  const back = participant.completion && participant.completion.redirect_url;
  show(sheet(
    h("h1", {}, "Thank you"),
    h("p", {}, "You chose not to take part, and nothing more will be recorded."),
    participant.platform === "mturk" ? h("p", {}, "Please return the HIT so that someone else can take it.") : null,
    back ? [h("p", {}, "You are being sent back to Prolific, which will ask you to return the study. If nothing happens, press the button."),
      h("a", { class: "btn primary big", href: back, target: "_top", "data-action": "return-prolific" }, "Return to Prolific")]
      : h("p", {}, "You may close this page.")));
  if (back) window.open(back, "_top");
}

function instructionsPage() {
  const agents = participant.progress.of;
  const start = h("button", { class: "btn primary big", type: "button", "data-action": "start" },
    study.tutorial ? "Start the tutorial" : "Start teaching");
  start.addEventListener("click", async () => {
    start.disabled = true;
    if (await post("/api/participant/start")) {
      await refresh();
      route();
    }
  });
  const icon = svg("svg", { viewBox: "0 0 100 100", class: "intro-robot", "aria-hidden": "true" });
  robotIcon(icon, "#56B4E9");
  show(plainSheet(
    h("h1", {}, "How it works"),
    h("div", { class: "intro" }, icon,
      h("div", {},
        h("p", {}, agents === 1
          ? `You will teach an agent (a small simulated robot) to do a few tasks in a ${participant.domain ?? "grid"} world. It starts knowing nothing, and learns only from you.`
          : `You will teach ${agents} agents (small simulated robots), one at a time, to do a few tasks in a ${participant.domain ?? "grid"} world. Each starts knowing nothing, and learns only from you.`),
        h("ul", { class: "intro-list" },
          h("li", {}, h("strong", {}, "Demonstrate"), " (", h("kbd", {}, "D"), "): move the agent to the task's goal with the arrow keys."),
          h("li", {}, h("strong", {}, "Let the agent try"), " (", h("kbd", {}, "T"), "): watch it act on its own, and press ", h("kbd", {}, "G"), " for a good move or ", h("kbd", {}, "B"), " for a bad one."),
          h("li", {}, "Switch tasks, ", h("strong", {}, "Stop"), " (", h("kbd", {}, "S"), ") and ", h("strong", {}, "Reset"), " (", h("kbd", {}, "R"), ") whenever you like."),
          h("li", {}, h("strong", {}, "Next agent"), " (", h("kbd", {}, "N"), ") opens once every task has at least one demonstrated move; go on when the agent does them well."),
        ),
        study.tutorial ? h("p", {}, "A short tutorial shows you each of these first.") : null,
        h("p", { class: "muted" }, "Your progress is saved as you go: if the page reloads, you continue where you were."))),
    h("div", { class: "actions" }, start)));
  start.focus();
}

// -- teaching ---------------------------------------------------------------------------------
async function teach(sessionId) {
  show();
  teacher = new Teacher({
    root: app,
    study,
    seq,
    participant,
    sessionId,
    tutorial: (t) => new Tutorial(t),
    onFinished: () => finished(),
    onLost: (error) => failure(error),
  });
  try {
    await teacher.start();
  } catch (error) {
    failure(error);
  }
}

async function finished() {
  teacher = null;
  await refresh();
  return route();
}

/** The attention check between two agents (a reload shows it again, as it was). */
function attentionPage(view) {
  show();
  check = new AttentionCheck({
    root: app,
    check: view,
    post,
    onDone: () => finished(),
  });
  check.start();
}

/** The introduction of the next agent, until the participant begins teaching it (a reload
 * shows it again: the server keeps whether the session was opened). */
function meetPage(current) {
  const index = participant.sessions.findIndex((s) => s.session_id === current.session_id);
  const previous = index > 0 ? participant.sessions[index - 1] : null;
  const icon = svg("svg", { viewBox: "0 0 100 100", class: "intro-robot", "aria-hidden": "true" });
  robotIcon(icon, current.colour.hex);
  const go = h("button", { class: "btn primary big", type: "button", "data-action": "begin-agent" }, h("kbd", {}, "Enter"), "Start teaching");
  go.addEventListener("click", async () => {
    go.disabled = true;
    if (await post(`/api/sessions/${current.session_id}/open`)) teach(current.session_id);
  });
  const newPlace = previous && previous.environment !== current.environment;
  show(plainSheet(
    h("p", { class: "eyebrow" }, `Agent ${current.position + 1} of ${participant.progress.of}`),
    h("h1", {}, `Meet the ${current.colour.name} agent`),
    h("div", { class: "intro" }, icon,
      h("div", {},
        previous?.kind === "tutorial" ? h("p", {}, "The tutorial is done. Now the study begins.") : null,
        h("p", {}, "This is a new agent: it has not seen anything you showed the others. Teach it every task, as well as you can."),
        newPlace || previous?.kind === "tutorial"
          ? h("p", {}, "It lives in a world called ", h("strong", {}, environmentTitle(current.environment)), newPlace && previous?.kind !== "tutorial" ? ", a new place." : ".")
          : null)),
    h("div", { class: "actions" }, go)));
  go.focus();
}

// -- the post-study questionnaire ---------------------------------------------------------------
function markInvalid(input, on) {
  if (on) input.setAttribute("aria-invalid", "true");
  else input.removeAttribute("aria-invalid");
}

/** One question's input: a labelled text box, or a fieldset of radio buttons whose legend is
 * the question. ``value()`` is the answer, or null when there is none. */
function questionField(question, index) {
  const id = `q-${index}`;
  const need = h("span", { class: "muted need" }, question.required ? " (required)" : " (optional)");
  const error = h("p", { class: "field-error", id: `${id}-error`, hidden: true });
  if (question.kind === "text") {
    const box = h("textarea", { id, name: question.id, rows: question.lines, maxlength: question.max_length,
      required: question.required, "aria-describedby": `${id}-error` });
    return {
      question, error, focus: () => box.focus(), invalid: (on) => markInvalid(box, on),
      element: h("div", { class: "question", "data-question": question.id }, h("label", { for: id }, question.text, need), box, error),
      value: () => (box.value.trim() ? box.value : null),
    };
  }
  const options = question.kind === "likert" ? question.labels : question.choices;
  const radios = options.map((option, k) => h("input", { type: "radio", id: `${id}-${k}`, name: question.id,
    value: question.kind === "likert" ? k + 1 : option, required: question.required }));
  const group = h("fieldset", { class: `question ${question.kind}`, "data-question": question.id, "aria-describedby": `${id}-error` },
    h("legend", {}, question.text, need),
    h("div", { class: question.kind === "likert" ? "scale" : "choices" },
      radios.map((radio, k) => h("label", { for: radio.id, class: "option" }, radio, h("span", {}, options[k])))),
    error);
  return {
    question, error, element: group,
    focus: () => (radios.find((r) => r.checked) ?? radios[0]).focus(),
    invalid: (on) => radios.forEach((r) => markInvalid(r, on)),
    value: () => {
      const checked = radios.find((r) => r.checked);
      if (!checked) return null;
      return question.kind === "likert" ? Number(checked.value) : checked.value;
    },
  };
}

function questionnairePage() {
  const questionnaire = study.questionnaire;
  const fields = questionnaire.questions.map(questionField);
  const message = h("p", { class: "form-error", role: "alert", hidden: true });
  const submit = h("button", { class: "btn primary big", type: "submit", "data-action": "submit-questionnaire" }, "Send the answers");
  const form = h("form", { class: "questionnaire", novalidate: true }, fields.map((f) => f.element), message, h("div", { class: "actions" }, submit));
  for (const field of fields) {
    field.element.addEventListener("input", () => {
      field.invalid(false);
      field.error.hidden = true;
    });
  }
  const complain = (text) => {
    message.hidden = false;
    message.textContent = text;
  };
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    const answers = {};
    const missing = [];
    for (const field of fields) {
      const value = field.value();
      field.invalid(false);
      field.error.hidden = true;
      if (value !== null) answers[field.question.id] = value;
      else if (field.question.required) missing.push(field);
    }
    if (missing.length) {
      for (const field of missing) {
        field.invalid(true);
        field.error.hidden = false;
        field.error.textContent = "Please answer this question.";
      }
      complain(missing.length === 1 ? "One question still needs an answer." : `${missing.length} questions still need an answer.`);
      missing[0].focus();
      return;
    }
    submit.disabled = true;
    try {
      await seq.post("/api/participant/questionnaire", { answers });
    } catch (error) {
      if (error instanceof ApiError && error.resync) {
        await refresh();
        return route();
      }
      if (error instanceof ApiError && error.status === 422) {
        complain(typeof error.detail === "string" ? error.detail : "Some answers could not be accepted.");
        submit.disabled = false;
        return;
      }
      return failure(error);
    }
    await refresh();
    route();
  });
  show(sheet(
    h("h1", {}, "A few questions"),
    h("p", {}, questionnaire.intro),
    form));
}

// -- completion -------------------------------------------------------------------------------
async function completionPage() {
  let completion;
  try {
    completion = await getJSON("/api/participant/completion", { onRetry: connection.down });
  } catch (error) {
    return failure(error);
  }
  const code = h("p", { class: "code", "data-testid": "completion-code" }, completion.code);
  const copy = h("button", { class: "btn quiet", type: "button" }, "Copy the code");
  copy.addEventListener("click", async () => {
    try {
      await navigator.clipboard.writeText(completion.code);
      copy.textContent = "Copied";
    } catch {
      const range = document.createRange();
      range.selectNodeContents(code);
      window.getSelection().removeAllRanges();
      window.getSelection().addRange(range);
      copy.textContent = "Selected: press Ctrl+C to copy";
    }
  });
  const parts = [
    h("h1", {}, "Thank you: you have finished"),
    h("p", {}, "Your completion code:"),
    h("div", { class: "code-row" }, code, copy),
  ];
  if (completion.mode === "mturk") {
    const form = h("form", { method: "POST", action: completion.submit_url, target: "_top", class: "submit-form" },
      Object.entries(completion.submit_fields).map(([name, value]) => h("input", { type: "hidden", name, value })),
      h("button", { class: "btn primary big", type: "submit", "data-action": "submit-hit" }, "Submit the HIT"));
    form.addEventListener("submit", async (event) => {
      event.preventDefault();
      form.querySelector("button").disabled = true;
      await recordSubmission();
      form.submit();
    });
    parts.push(h("p", {}, "Press the button to submit your work to Mechanical Turk. The code is sent with it."), form);
  } else if (completion.mode === "prolific") {
    // Prolific's guidance: send the participant back automatically; the button is the fallback.
    const link = h("a", { class: "btn primary big", href: completion.redirect_url, target: "_top", "data-action": "return-prolific" }, "Return to Prolific");
    const back = async () => {
      await recordSubmission();
      window.open(completion.redirect_url, "_top");
    };
    link.addEventListener("click", (event) => {
      event.preventDefault();
      back();
    });
    parts.push(h("p", {}, "You are being sent back to Prolific, which records that you completed the study. If nothing happens, press the button."), link);
    show(sheet(...parts));
    back();
    return;
  } else {
    parts.push(h("p", {}, "Please give this code to the experimenter. You may close this page."));
  }
  show(sheet(...parts));
}

async function recordSubmission() {
  await refresh();
  if (participant.status !== "completed") return; // recorded already
  try {
    await seq.post("/api/participant/submission");
  } catch (error) {
    console.warn("could not record the submission", error);
  }
}

// -- start ------------------------------------------------------------------------------------
document.addEventListener("keydown", (event) => {
  // Enter on a page whose single main action is focused works natively; this is for the
  // between-agents page, where Enter starts teaching wherever the focus is.
  if (event.key === "Enter" && !teacher) {
    const begin = app.querySelector('[data-action="begin-agent"]');
    if (begin && document.activeElement !== begin) {
      event.preventDefault();
      begin.click();
    }
  }
});

try {
  await refresh();
  await route();
} catch (error) {
  failure(error);
}

