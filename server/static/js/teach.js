// The teaching page for one learning session (one agent, or the tutorial's agent): the grid,
// the task selector, the modes, feedback, and the agent's own steps about every half second.
// Everything shown comes from the server's answers, so a reload continues exactly here.

import { ApiError, getJSON } from "./api.js";
import { capitalise, environmentTitle, h, sleep } from "./dom.js";
import { GridView, TERRAIN, colourLetter, gravityRule, kindLabel, kindsOf, robotIcon, svg, swatch } from "./grid.js";

const STEP_MS = 500; // the agent's pace when it acts on its own
const MAX_QUEUED_MOVES = 2; // arrow presses waiting for the server (key repeat is dropped)
const FLASH_MS = 700;

const KEYS = {
  ArrowUp: "UP",
  ArrowDown: "DOWN",
  ArrowLeft: "LEFT",
  ArrowRight: "RIGHT",
};

/** The machines that enter a terrain, in words: "trellis", "plow or the quad bike". */
function machinesOf(env, terrain) {
  return terrain.machines.map((m) => kindLabel(env, "machine", m).toLowerCase()).join(" or the ");
}

export class Teacher {
  /**
   * @param {object} options  {root, study, seq, participant (ParticipantState), sessionId,
   *                           onFinished(response), onLost(error), tutorial (factory or null)}
   */
  constructor(options) {
    Object.assign(this, options);
    this.closed = false;
    this.listeners = [];
    this.notice = null;
    this.lastEnd = null;
    this.onKey = (event) => this.key(event);
  }

  async start() {
    const view = await getJSON(`/api/sessions/${this.sessionId}`);
    this.summary = view.summary;
    this.env = view.environment;
    this.t = view.teaching;
    this.brief = view.participant;
    this.isTutorial = this.summary.kind === "tutorial";
    this.render();
    if (this.isTutorial && this.tutorial) {
      this.guide = this.tutorial(this);
    }
    document.addEventListener("keydown", this.onKey);
    this.focusWatch = setInterval(() => this.showFocusHint(), 1000);
    this.update();
    if (this.t.mode === "agent") this.agentLoop();
    if (this.t.learning.pending > 0) this.watchLearning();
  }

  close() {
    this.closed = true;
    document.removeEventListener("keydown", this.onKey);
    clearInterval(this.focusWatch);
    this.resizer?.disconnect();
  }

  on(listener) {
    this.listeners.push(listener);
  }

  emit(event) {
    for (const listener of this.listeners) listener(event);
  }

  get url() {
    return `/api/sessions/${this.sessionId}`;
  }

  taskName(index = this.t.task) {
    return this.env.tasks[index]?.name ?? `task ${index + 1}`;
  }

  // -- drawing ----------------------------------------------------------------------------
  render() {
    const { summary, env, study } = this;
    const colour = summary.colour;
    const progress = this.participant.progress;
    const label = this.isTutorial ? "Tutorial" : `Agent ${summary.position + 1} of ${progress.of}`;
    const dots = this.isTutorial
      ? null
      : h("span", { class: "progress-dots", "aria-hidden": "true" },
          Array.from({ length: progress.of }, (_, i) =>
            h("span", { class: `dot ${i < summary.position ? "done" : i === summary.position ? "current" : ""}` })));

    this.board = h("div", { class: "board" });
    this.flashBox = h("div", { class: "flash", "aria-hidden": "true" });
    this.focusHint = h("button", { class: "focus-hint", hidden: true, onclick: () => window.focus() }, "Click here so that the keys reach the page");
    const icon = svg("svg", { viewBox: "0 0 100 100", class: "agent-icon", "aria-hidden": "true" });
    robotIcon(icon, colour.hex);
    this.featureLine = h("p", { class: "agent-feature" });
    const agentCard = h("div", { class: "agent-card" }, icon,
      h("div", {},
        h("p", { class: "agent-name" }, this.isTutorial ? "Your practice agent" : `The ${colour.name} agent`),
        h("p", { class: "agent-note" }, this.isTutorial
          ? "Practise here; nothing here counts."
          : "New: it knows nothing the others learned."),
        this.featureLine));

    this.tutorialCard = h("section", { class: "tutorial-card", hidden: true, "aria-live": "polite" });
    // The status line changes with every move; what a participant must notice (an episode
    // ended, the agent learning, feedback recorded, a refusal) is also said in the log below,
    // which screen readers announce.
    this.status = h("p", { class: "status" });
    this.announcements = h("div", { class: "visually-hidden", role: "log", "aria-live": "polite", "data-testid": "announcements" });
    this.gridText = h("p", { class: "visually-hidden", id: `grid-text-${this.sessionId}`, "data-testid": "grid-text" });
    this.learning = h("p", { class: "learning", hidden: true },
      h("span", { class: "spinner", "aria-hidden": "true" }), " ",
      h("span", { class: "learning-text" }, "The agent is learning from your last episode…"));

    this.taskButtons = env.tasks.map((task, index) =>
      h("button", { type: "button", class: "task", "data-task": index, onclick: () => this.selectTask(index) },
        h("kbd", {}, String(index + 1)),
        h("span", { class: "task-name" }, task.name),
        h("span", { class: "task-count" })));
    const tasks = h("section", { class: "tasks" }, h("h2", {}, "Task"), h("div", { class: "task-list" }, this.taskButtons));

    const button = (name, text, key, handler, extra = "") =>
      h("button", { type: "button", class: `btn mode-btn ${extra}`, "data-action": name, onclick: handler }, h("kbd", {}, key), text);
    this.buttons = {
      demonstrate: button("demonstrate", "Demonstrate", "D", () => this.setMode("demonstrate")),
      agent: button("agent", "Let the agent try", "T", () => this.setMode("agent")),
      stop: button("stop", "Stop", "S", () => this.stop()),
      reset: button("reset", "Reset", "R", () => this.reset()),
    };

    this.goodButton = h("button", { type: "button", class: "btn feedback-btn good", "data-action": "good", onclick: () => this.feedback(1) },
      h("kbd", {}, "G"), h("span", { class: "fb-symbol", "aria-hidden": "true" }, "+"), "Good");
    this.badButton = h("button", { type: "button", class: "btn feedback-btn bad", "data-action": "bad", onclick: () => this.feedback(-1) },
      h("kbd", {}, "B"), h("span", { class: "fb-symbol", "aria-hidden": "true" }, "−"), "Bad");
    const controls = h("div", { class: "controls", role: "toolbar", "aria-label": "Teaching" },
      h("div", { class: "mode-row" }, Object.values(this.buttons)),
      h("div", { class: "feedback-row", role: "group", "aria-label": "Feedback on the agent's moves" },
        h("span", { class: "feedback-label" }, "Feedback"), this.goodButton, this.badButton));
    const stage = h("section", { class: "stage", "aria-label": "The grid world" },
      // Above the grid, not over it: the hint never hides the first row or the goals' labels.
      this.focusHint,
      h("div", { class: "board-frame" }, this.board, this.flashBox),
      this.gridText,
      controls,
      h("p", { class: "hint" }, h("kbd", {}, "←"), h("kbd", {}, "↑"), h("kbd", {}, "↓"), h("kbd", {}, "→"),
        " move the agent: a lesson when demonstrating, just a move when no mode is on."),
      this.legend());

    this.nextButton = h("button", { type: "button", class: "btn primary next-btn", "data-action": "next", onclick: () => this.next() },
      h("kbd", {}, "N"), this.isTutorial ? "Finish the tutorial" : "Next agent");
    this.nextReason = h("p", { class: "next-reason", id: `next-reason-${this.sessionId}` });
    this.nextButton.setAttribute("aria-describedby", this.nextReason.id);
    const next = h("section", { class: "next" }, this.nextButton, this.nextReason);

    const panel = h("aside", { class: "panel", "aria-label": "Teaching controls" },
      agentCard, this.tutorialCard, this.status, this.announcements, this.learning, tasks, next, this.rules());

    const header = h("header", { class: "topbar" },
      h("div", { class: "topbar-title" }, h("img", { src: "/static/img/robot.svg", alt: "", width: 28, height: 28 }), study.title),
      h("div", { class: "topbar-place" }, this.isTutorial ? `Tutorial: ${capitalise(env.domain)}` : environmentTitle(env.name)),
      h("div", { class: "progress", "data-testid": "progress" }, h("span", { class: "progress-label" }, label), dots));

    this.dialog = h("dialog", { class: "confirm" });
    this.page = h("div", {
      class: `teach-page domain-${env.domain}`,
      "data-session": this.sessionId,
      "data-kind": summary.kind,
      "data-environment": env.name,
    }, header, h("div", { class: "teach-main" }, stage, panel), this.dialog);
    this.root.replaceChildren(this.page);
    this.grid = new GridView(this.board, env, { reveal: study.reveal_gravity });
    this.grid.root.setAttribute("aria-describedby", this.gridText.id);
    this.resizer = new ResizeObserver(() => this.fit());
    this.resizer.observe(this.board.parentElement);
  }

  /** The grid as large as its frame allows, at its own aspect ratio. */
  fit() {
    const frame = this.board.parentElement;
    const ratio = this.env.width / this.env.height;
    const width = frame.clientWidth;
    const height = frame.clientHeight || width / ratio;
    const fitted = Math.max(120, Math.min(width, height * ratio));
    this.board.style.width = `${Math.floor(fitted)}px`;
    this.board.style.height = `${Math.floor(fitted / ratio)}px`;
  }

  legend() {
    const { env } = this;
    const items = [];
    const item = (node, label) => items.push(h("li", {}, node, h("span", {}, label)));
    item(swatch("goal"), "Goal of the selected task");
    if (env.domain === "navigation") {
      item(swatch("terrain", "wall"), "Wall");
      item(swatch("terrain", "floor"), "Floor");
    } else if (env.domain === "farming") {
      const present = new Set(env.terrain.flat());
      for (const terrain of ["dirt", "soil", "grass", "crops"]) {
        if (present.has(terrain)) item(swatch("terrain", terrain), TERRAIN[terrain].label);
      }
      // A study's own terrains and machines, after the built-in ones.
      for (const kind of kindsOf(env).values()) {
        if (kind.built_in) continue;
        if (kind.category === "terrain" && present.has(kind.name)) {
          const machine = kind.machines?.length ? `: needs the ${machinesOf(env, kind)}` : "";
          item(swatch("terrain", kind.name, env), `${kind.label} (${kind.initial})${machine}`);
        } else if (kind.category === "machine" && (env.machines ?? []).some((m) => m.machine === kind.name)) {
          const terrain = kind.terrain ? `: the machine for ${kindLabel(env, "terrain", kind.terrain).toLowerCase()}` : "";
          item(swatch("machine", kind.name, env), `${kind.label} (${kind.initial})${terrain}`);
        }
      }
    } else if (env.domain === "gravity") {
      for (const colour of new Set((env.colours ?? []).map((c) => c.colour))) {
        const direction = this.study.reveal_gravity ? env.gravity_of_colour?.[colour] : null;
        item(swatch("colour", colour, env), `${capitalise(colour)} cell (${colourLetter(env, colour)}): sets the gravity${direction ? ` ${direction}` : ""}`);
      }
      item(swatch("gravity", "north"), "The agent's gravity");
    }
    return h("ul", { class: "legend", "aria-label": "Legend" }, items);
  }

  rules() {
    const { env } = this;
    const lines = [];
    if (env.domain === "navigation") {
      lines.push("Walls (dark, hatched cells) block the agent; it cannot see them itself.");
      lines.push("Each task is to reach its goal, marked with its name; the selected one has a ★.");
    } else if (env.domain === "farming") {
      lines.push("Drive over a machine to pick it up; the agent carries one machine at a time and leaves the one it had.");
      lines.push("Soil can only be entered carrying the plow, grass (young crops) with the sprinkler, grown crops with the harvester. Bare dirt is free.");
      for (const kind of kindsOf(env).values()) {
        if (kind.category === "terrain" && !kind.built_in && kind.machines?.length) {
          lines.push(`${kind.label} can only be entered carrying the ${machinesOf(env, kind)}.`);
        }
      }
      lines.push("Each task is to reach its field; the selected one has a ★.");
    } else if (env.domain === "gravity") {
      lines.push("The agent has a gravity, shown by the arrow on it: it cannot move against it (gravity north: it cannot move down).");
      lines.push(this.study.reveal_gravity
        ? "On a coloured cell, the next move (or staying) first sets the gravity to the direction its arrow shows."
        : "On a coloured cell, the next move (or staying) first changes the gravity; which direction each colour sets is for you to find out by trying.");
      lines.push("Each task is to reach its goal, marked with its name; the selected one has a ★.");
    }
    lines.push(`An agent's try ends at the goal or after ${env.horizon} moves.`);
    return h("details", { class: "rules" }, h("summary", {}, "How this world works"),
      h("ul", {}, lines.map((line) => h("li", {}, line))));
  }

  update() {
    const { t, env } = this;
    this.grid.setTask(t.task);
    this.grid.setAgent(t.agent, this.summary.colour.hex);
    this.page.dataset.mode = t.mode;
    this.page.dataset.task = t.task;
    this.page.dataset.actions = t.actions;
    this.page.dataset.episodes = t.episodes;
    this.page.dataset.pending = t.learning.pending;
    this.page.dataset.episodeActions = t.episode ? t.episode.actions : 0;
    this.page.dataset.seq = this.seq.nextSeq;
    this.taskButtons.forEach((button, index) => {
      const selected = index === t.task;
      button.setAttribute("aria-pressed", String(selected));
      const count = t.demonstrated[index] ?? 0;
      button.dataset.count = count;
      button.classList.toggle("demonstrated", count > 0);
      button.querySelector(".task-count").textContent = count > 0 ? `✓ ${count} move${count === 1 ? "" : "s"} shown` : "not shown yet";
    });
    this.buttons.demonstrate.setAttribute("aria-pressed", String(t.mode === "demonstrate"));
    this.buttons.agent.setAttribute("aria-pressed", String(t.mode === "agent"));
    this.buttons.stop.disabled = t.mode === "idle";
    const atGoal = this.atGoal();
    this.buttons.reset.classList.toggle("prompt", t.mode === "idle" && atGoal);
    const feedbackOn = t.can_give_feedback;
    this.goodButton.disabled = !feedbackOn;
    this.badButton.disabled = !feedbackOn;
    const reason = this.finishBlocked();
    this.nextButton.disabled = reason !== null;
    this.nextReason.textContent = reason ?? (this.isTutorial ? "" : "Every task has at least one demonstrated move: go on when the agent does them well.");
    this.nextReason.classList.toggle("ok", reason === null);
    this.featureLine.textContent = t.agent?.carrying !== undefined
      ? `Carrying: ${t.agent.carrying === "none" ? "nothing" : kindLabel(env, "machine", t.agent.carrying)}`
      : t.agent?.gravity !== undefined
        ? capitalise(gravityRule(t.agent.gravity))
        : "";
    const learning = t.learning.pending > 0;
    if (this.wasLearning !== undefined && learning !== this.wasLearning) {
      this.announce(learning
        ? "The agent is learning from your last episode."
        : "The agent has learned from your last episode.");
    }
    this.wasLearning = learning;
    this.learning.hidden = !learning;
    this.learning.querySelector(".learning-text").textContent = t.mode === "agent"
      ? "The agent is still learning; it starts moving as soon as it is done."
      : "The agent is learning; you can go on teaching meanwhile.";
    this.status.textContent = this.statusText(atGoal);
    this.gridText.textContent = this.describeGrid();
    this.guide?.render();
  }

  /** What the grid shows, in words (the drawing's text for screen readers). */
  describeGrid() {
    const { t, env } = this;
    const place = ([r, c]) => `row ${r + 1}, column ${c + 1}`;
    const parts = [`A grid of ${env.height} rows and ${env.width} columns, counted from the top left.`];
    if (t.agent) {
      parts.push(`The agent is at ${place([t.agent.row, t.agent.column])}${this.atGoal() ? ", on the goal" : ""}.`);
      if (t.agent.carrying !== undefined) {
        parts.push(t.agent.carrying === "none" ? "It carries no machine." : `It carries the ${kindLabel(env, "machine", t.agent.carrying).toLowerCase()}.`);
      }
      if (t.agent.gravity !== undefined) parts.push(`Its ${gravityRule(t.agent.gravity)}.`);
    }
    const goal = env.tasks[t.task].goal_cells;
    parts.push(goal.length === 1
      ? `The goal of the selected task, “${this.taskName()}”, is at ${place(goal[0])}.`
      : `The goal of the selected task, “${this.taskName()}”, is the field from ${place(goal[0])} to ${place(goal[goal.length - 1])}.`);
    for (const { row, column, machine } of env.machines ?? []) parts.push(`The ${kindLabel(env, "machine", machine).toLowerCase()} is at ${place([row, column])}.`);
    for (const { row, column, colour } of env.colours ?? []) {
      const direction = this.study.reveal_gravity ? env.gravity_of_colour?.[colour] : null;
      parts.push(`A ${colour} cell (${colourLetter(env, colour)}) at ${place([row, column])}${direction ? ` sets the gravity ${direction}` : ""}.`);
    }
    return parts.join(" ");
  }

  modeText() {
    const task = `“${this.taskName()}”`;
    if (this.t.mode === "demonstrate") return `Demonstrating ${task}: walk the agent to its goal with the arrow keys.`;
    if (this.t.mode === "agent") return `The agent is trying ${task}. Press G after a good move, B after a bad one; S stops it.`;
    return "No mode on: the arrow keys just move the agent.";
  }

  /** Said to screen readers (a polite live log; the last few messages stay). */
  announce(text) {
    if (this.announcements.lastElementChild?.textContent === text) return;
    this.announcements.appendChild(h("p", {}, text));
    while (this.announcements.children.length > 5) this.announcements.firstElementChild.remove();
  }

  atGoal() {
    const agent = this.t.agent;
    if (!agent) return false;
    return this.env.tasks[this.t.task].goal_cells.some(([r, c]) => r === agent.row && c === agent.column);
  }

  finishBlocked() {
    if (this.isTutorial && this.guide && !this.guide.complete) return "Do the tutorial's steps first.";
    if (!this.t.can_finish) {
      const missing = this.t.demonstrated.map((n, k) => (n === 0 ? `“${this.taskName(k)}”` : null)).filter(Boolean);
      return missing.length
        ? `Every task needs at least one demonstrated move first. Not yet: ${missing.join(", ")}.`
        : capitalise(this.t.finish_blocked ?? "not yet");
    }
    return null;
  }

  /** What stopped the last move, in words (the agent stayed where it was). */
  blockedText() {
    const { direction, mode } = this.blocked;
    if (mode === "agent") return `The agent's last move (${direction}) was blocked: it stayed where it was, and the move still counts.`;
    if (mode === "demonstrate") return `Blocked: the agent could not move ${direction} and stayed where it was; the move still counts as demonstrated.`;
    return `Blocked: the agent could not move ${direction} and stayed where it was.`;
  }

  statusText(atGoal) {
    if (this.notice && this.notice.until > Date.now()) return this.notice.text;
    const text = this.modeStatus(atGoal);
    return this.blocked ? `${this.blockedText()} ${text}` : text;
  }

  modeStatus(atGoal) {
    const { t, env } = this;
    const task = `“${this.taskName()}”`;
    if (t.mode === "demonstrate") {
      const moves = t.episode ? ` (${t.episode.actions} move${t.episode.actions === 1 ? "" : "s"} so far)` : "";
      return `Demonstrating ${task}${moves}: walk the agent to the goal with the arrow keys; reaching it ends the demonstration.`;
    }
    if (t.mode === "agent") {
      const moves = t.episode ? ` (${t.episode.actions} of at most ${env.horizon} moves)` : "";
      return `The agent is trying ${task}${moves}. Press G after a good move, B after a bad one; Stop (S) stops it.`;
    }
    const end = this.lastEnd;
    if (end?.reason === "goal" && end.kind === "demonstrate") {
      return `Well done: the demonstration reached the goal of ${task}. Press T to let the agent try from a random start, D to demonstrate again, or Reset (R).`;
    }
    if (end?.reason === "goal" && end.kind === "agent") {
      return `The agent reached the goal of ${task}. Press T to let it try again from a random start, or D to demonstrate.`;
    }
    if (end?.reason === "horizon") {
      return `The agent used its ${env.horizon} moves without reaching the goal of ${task}. Press T to let it try again from here, or Reset (R) for a new random start.`;
    }
    if (end?.reason === "mode" && end.kind === "demonstrate") {
      return `Demonstration stopped before the goal; the agent learns from the moves you showed. Press Reset (R) for a new random start, or go on.`;
    }
    if (atGoal) {
      return `The agent is at the goal of ${task}. T (let it try) or D (demonstrate) starts from a random place; Reset (R) draws one now; the arrow keys move it.`;
    }
    return `Demonstrate (D) to show the agent ${task}, or let it try (T). With no mode on, the arrows just move the agent.`;
  }

  say(text, ms = 4000) {
    this.notice = { text, until: Date.now() + ms };
    this.status.textContent = text;
    this.announce(text);
    setTimeout(() => {
      if (!this.closed && this.notice && this.notice.until <= Date.now()) {
        this.notice = null;
        this.update();
      }
    }, ms + 50);
  }

  flash(kind) {
    const box = this.flashBox;
    box.replaceChildren(h("span", { class: "flash-badge" },
      h("span", { class: "fb-symbol" }, kind === "good" ? "+" : "−"), kind === "good" ? "Good" : "Bad"));
    box.classList.remove("good", "bad", "on");
    void box.offsetWidth; // restart the animation
    box.classList.add(kind, "on");
    clearTimeout(this.flashTimer);
    this.flashTimer = setTimeout(() => box.classList.remove("on"), FLASH_MS);
  }

  showFocusHint() {
    if (this.closed) return;
    // Inside the platform's iframe the keys only arrive once the page has the focus.
    this.focusHint.hidden = document.hasFocus() || window.top === window;
  }

  // -- requests ---------------------------------------------------------------------------
  /** Queue a POST; ``body`` is called when its turn comes (null skips it). */
  async act(path, body, kind) {
    let modeBefore = null;
    let taskBefore = null;
    try {
      const url = () => `${this.url}/${typeof path === "function" ? path() : path}`;
      const response = await this.seq.post(url, () => {
        if (this.closed) return null;
        const payload = typeof body === "function" ? body() : body;
        if (payload !== null) {
          modeBefore = this.t.mode;
          taskBefore = this.t.task;
        }
        return payload;
      });
      if (!response) return null;
      this.apply(response, kind, modeBefore, taskBefore);
      return response;
    } catch (error) {
      await this.failed(error);
      return null;
    }
  }

  apply(response, kind, modeBefore, taskBefore) {
    this.brief = response.participant;
    const before = this.t.agent;
    if (response.session) this.t = response.session;
    const outcome = response.outcome;
    const after = this.t.agent;
    // A move (the participant's or the agent's) that left the agent on its cell is shown and
    // said: otherwise only a move counter would change.
    this.blocked = ["move", "agent-step"].includes(kind) && outcome.action && outcome.action !== "STAY"
      && before && after && before.row === after.row && before.column === after.column
      ? { direction: outcome.action.toLowerCase(), mode: modeBefore }
      : kind === "feedback" ? this.blocked : null;
    if (this.blocked) this.grid.bump(outcome.action);
    if (outcome.episode_ended) {
      this.lastEnd = { reason: outcome.episode_ended, kind: modeBefore };
    } else if (["reset", "mode", "task"].includes(kind) || (kind === "move" && modeBefore === "demonstrate")) {
      this.lastEnd = null;
    }
    if (outcome.feedback) this.flash(outcome.feedback > 0 ? "good" : "bad");
    if (outcome.new_start) {
      // No episode starts on the goal: the server put the agent at a random start first.
      const what = this.t.mode === "agent" ? "it tries from a random start" : "it starts from a random place: walk it to the goal";
      this.say(`The agent was on the goal of “${this.taskName()}” already, so ${what}.`, 5000);
    }
    if (!this.closed) {
      // Said before update(), which says that the agent is learning from the episode.
      if (outcome.episode_ended) this.announce(`Episode ended. ${this.statusText(this.atGoal())}`);
      if (outcome.feedback) this.announce(`Feedback recorded: ${outcome.feedback > 0 ? "good" : "bad"}.`);
      if (kind === "mode" && this.t.mode !== modeBefore && !outcome.episode_ended) this.announce(this.modeText());
      if (kind === "task" && this.t.task !== taskBefore) this.announce(`Task “${this.taskName()}” selected.`);
      if (this.blocked) this.announce(this.blockedText());
      this.update();
    }
    this.emit({ kind, outcome, modeBefore, taskBefore, state: this.t });
    if (this.t.learning.pending > 0) this.watchLearning();
  }

  async failed(error) {
    if (this.closed) return;
    if (error instanceof ApiError && error.status === 401) {
      this.close();
      this.onLost(error);
      return;
    }
    // The page and the server disagree (another tab, a lost answer): take the server's word.
    try {
      const view = await getJSON(this.url);
      this.t = view.teaching;
      this.brief = view.participant;
      if (view.summary.status !== "active") {
        this.close();
        this.onFinished({ participant: view.participant, session: view.teaching });
        return;
      }
    } catch (refresh) {
      console.warn("could not refresh the session", refresh);
    }
    this.update();
    if (error instanceof ApiError && error.resync) {
      this.say("The study was continued in another tab or window; this page has been brought up to date. Please go on here, or in the other one, but not in both.", 8000);
      return;
    }
    this.say(error instanceof ApiError ? `Not done: ${error.detail}` : "Something went wrong; please try again.");
  }

  move(action) {
    if (this.t.mode === "agent") {
      this.say("The agent is acting on its own: press Stop (S) before moving it yourself.", 3000);
      return;
    }
    if (this.seq.pending > MAX_QUEUED_MOVES) return;
    this.act("move", () => (this.t.mode === "agent" ? null : { action }), "move");
  }

  selectTask(index) {
    if (index >= this.env.tasks.length) return;
    this.act("task", () => (index === this.t.task ? null : { task: index }), "task");
  }

  setMode(mode) {
    this.act("mode", () => (mode === this.t.mode ? null : { mode }), "mode").then((response) => {
      if (response && this.t.mode === "agent") this.agentLoop();
    });
  }

  stop() {
    // Stops the agent (its episode ends), or a demonstration before its goal: that one ends
    // without the final STAY, which would tell the agent this place is the goal (reaching the
    // goal ends a demonstration, with its STAY, by itself).
    const agentEpisode = () => this.t.mode === "agent" && this.t.episode;
    this.act(
      () => (agentEpisode() ? "end-episode" : "mode"),
      () => (agentEpisode() ? {} : this.t.mode === "idle" ? null : { mode: "idle" }),
      "stop",
    );
  }

  reset() {
    this.act("reset", {}, "reset");
  }

  feedback(value) {
    if (!this.t.can_give_feedback) {
      this.say("Feedback is about the agent's own moves: let it try (T) first.", 3000);
      return;
    }
    this.act("feedback", () => (this.t.can_give_feedback ? { feedback: value } : null), "feedback");
  }

  async next() {
    const reason = this.finishBlocked();
    if (reason) {
      this.say(`Not yet. ${reason}`, 5000);
      this.nextReason.classList.remove("shake");
      void this.nextReason.offsetWidth;
      this.nextReason.classList.add("shake");
      return;
    }
    if (!this.isTutorial && !(await this.confirmNext())) return;
    const response = await this.act("finish", {}, "finish");
    if (response && response.participant.current_session_id !== this.sessionId) {
      this.close();
      this.onFinished(response);
    }
  }

  confirmNext() {
    return new Promise((resolve) => {
      const done = (answer) => {
        this.dialog.close();
        resolve(answer);
      };
      // After the last agent there is no next one: the study ends (or its questions follow).
      const last = this.summary.position + 1 >= this.participant.progress.of;
      const yes = h("button", { type: "button", class: "btn primary", "data-action": "confirm-next", onclick: () => done(true) },
        h("kbd", {}, "Enter"), last ? "Yes, finish teaching" : "Yes, next agent");
      const no = h("button", { type: "button", class: "btn", "data-action": "cancel-next", onclick: () => done(false) }, h("kbd", {}, "Esc"), "Keep teaching");
      const after = !last
        ? "You cannot come back to this agent once you move on."
        : this.study.questionnaire
          ? "This is the last agent: a few questions follow, and you cannot come back to it."
          : "This is the last agent: the study ends here, and you cannot come back to it.";
      this.dialog.replaceChildren(
        h("h2", {}, `Finish teaching the ${this.summary.colour.name} agent?`),
        h("p", {}, after),
        h("div", { class: "dialog-buttons" }, no, yes));
      this.dialog.oncancel = (event) => {
        event.preventDefault();
        done(false);
      };
      this.dialog.showModal();
      yes.focus();
    });
  }

  // -- the agent acting on its own ----------------------------------------------------------
  async agentLoop() {
    if (this.looping) return;
    this.looping = true;
    try {
      while (!this.closed && this.t.mode === "agent") {
        if (this.t.learning.pending > 0) {
          const learning = await getJSON(`${this.url}/learning?wait=5`);
          if (this.closed || this.t.mode !== "agent") break;
          this.t.learning = learning;
          this.update();
          continue;
        }
        const started = performance.now();
        const response = await this.act(
          "agent-step",
          () => (this.t.mode === "agent" && this.t.learning.pending === 0 ? {} : null),
          "agent-step",
        );
        const wait = STEP_MS - (performance.now() - started);
        if (!response && this.t.mode === "agent") await sleep(STEP_MS);
        else if (wait > 0) await sleep(wait);
      }
    } finally {
      this.looping = false;
    }
  }

  async watchLearning() {
    if (this.watching) return;
    this.watching = true;
    try {
      while (!this.closed && this.t.learning.pending > 0) {
        const before = this.t.learning;
        const learning = await getJSON(`${this.url}/learning?wait=10`);
        if (this.closed) break;
        // An answer from before a newer request's state is not newer than it.
        if (this.t.learning === before || learning.updates >= this.t.learning.updates) {
          this.t.learning = learning;
          this.update();
        }
      }
    } catch (error) {
      console.warn("could not follow the agent's learning", error);
    } finally {
      this.watching = false;
    }
  }

  // -- keys --------------------------------------------------------------------------------
  key(event) {
    if (this.closed || event.ctrlKey || event.metaKey || event.altKey) return;
    if (this.dialog.open || document.querySelector("dialog[open]")) return; // the withdrawal too
    const target = event.target;
    if (target instanceof HTMLElement && target.closest("input, textarea, select, [contenteditable]")) return;
    if (KEYS[event.key]) {
      event.preventDefault(); // never scroll the page
      this.move(KEYS[event.key]);
      return;
    }
    if (event.key === " " && !(target instanceof HTMLElement && target.closest("button, a, summary"))) {
      event.preventDefault();
      return;
    }
    if (event.repeat) return;
    const key = event.key.toLowerCase();
    const handlers = {
      d: () => this.setMode("demonstrate"),
      t: () => this.setMode("agent"),
      s: () => this.stop(),
      r: () => this.reset(),
      n: () => this.next(),
      g: () => this.feedback(1),
      "+": () => this.feedback(1),
      "=": () => this.feedback(1), // the "+" key unshifted
      b: () => this.feedback(-1),
      "-": () => this.feedback(-1),
    };
    if (handlers[key]) {
      event.preventDefault();
      handlers[key]();
    } else if (/^[1-9]$/.test(key)) {
      event.preventDefault();
      this.selectTask(Number(key) - 1);
    }
  }
}
