// The interactive tutorial: steps over the teaching page of the tutorial's agent, each done only
// when the participant has done it. The step reached is kept on the server with the rest of the
// participant's state, so that a reload, or another browser, continues at the same step.

import { h } from "./dom.js";

function count(counters, name) {
  counters[name] = (counters[name] ?? 0) + 1;
  return counters[name];
}

/**
 * A demonstration of ``task`` that reached its goal: the server says so in the answer to the
 * move that got there (a demonstration stopped with S, or by switching task or resetting, ends
 * too, but teaches the task only partly).
 */
function demonstratedToGoal(event, task) {
  return event.kind === "move" && event.modeBefore === "demonstrate" && event.taskBefore === task
    && event.outcome.goal_reached && event.outcome.episode_ended === "goal";
}

/** The rule for going on, as the study applies it (the server refuses Next agent until then). */
export const RULE = "In the study, Next agent opens once every task has at least one demonstrated move (stopping early counts too; reaching the goal teaches more).";

/** The names of the tasks with no demonstrated move yet, quoted. */
function notShown(state, env) {
  return state.demonstrated.map((n, k) => (n === 0 ? `“${env.tasks[k].name}”` : null)).filter(Boolean);
}

function steps(teacher) {
  const { env } = teacher;
  const [first, second] = env.tasks.map((task) => `“${task.name}”`);
  const agents = teacher.participant.progress.of;
  const domainHint = {
    navigation: "Walls (dark, hatched) block the way.",
    farming: "Soil can only be entered with the plow: drive over the plow first.",
    gravity: "The arrow on the agent is its gravity: it cannot move against it. Coloured cells change it.",
  }[env.domain] ?? "";
  const placeHint = env.domain === "farming" ? " Driving over a machine picks it up." : "";
  return [
    {
      id: "move",
      title: "Move the agent",
      text: `This is your practice agent. Press the arrow keys to move it (3 moves). No mode is on, so these moves teach it nothing.${placeHint}`,
      done: (e, n) => e.kind === "move" && e.modeBefore === "idle" && count(n, "moves") >= 3,
    },
    {
      id: "demonstrate",
      title: "Show it a task",
      text: `The selected task is ${first} (★). Press Demonstrate (D), then walk the agent to its goal with the arrow keys; reaching it ends the demonstration. For this step, go all the way to the goal: Stop (S) ends a demonstration earlier. ${domainHint}`,
      done: (e) => demonstratedToGoal(e, 0),
    },
    {
      id: "try",
      title: "Let the agent try",
      text: "Press Let the agent try (T). The agent is on the goal already, so it first goes to a random start; then it acts on its own, a step every half second, with what it has learned so far. Watch a few steps.",
      done: (e, n) => e.kind === "agent-step" && (count(n, "steps") >= 3 || Boolean(e.outcome.episode_ended)),
    },
    {
      id: "feedback",
      title: "Tell it how it is doing",
      text: "While the agent moves, press G after a good move or B after a bad one. If the agent has stopped, press T: it tries again (from a random start if it reached the goal).",
      done: (e) => e.kind === "feedback",
    },
    {
      id: "stop",
      title: "Take back control",
      text: "Press Stop (S): the agent stops and no mode is on.",
      already: (t) => t.mode === "idle",
      done: (e) => e.state.mode === "idle",
    },
    {
      id: "switch",
      title: "Switch tasks",
      text: `Select the task ${second} with its button or the key 2. Demonstrations and feedback always belong to the selected task.`,
      done: (e) => e.kind === "task" && e.state.task === 1,
    },
    {
      id: "reset",
      title: "Start again",
      text: "Press Reset (R): the agent jumps to a random start for the selected task, away from its goal.",
      done: (e) => e.kind === "reset",
    },
    {
      id: "place",
      title: "Choose where to start",
      text: "You can also choose where a lesson starts: with no mode on, the arrow keys move the agent without teaching it. Move it 3 steps.",
      done: (e, n) => e.kind === "move" && e.modeBefore === "idle" && count(n, "moves") >= 3,
    },
    {
      id: "demonstrate-second",
      title: env.tasks.length > 2 ? "Demonstrate the other tasks" : "Demonstrate the other task",
      text: (t) => {
        const missing = notShown(t, env);
        const which = missing.length ? missing.join(" and ") : second;
        return `Now demonstrate ${which}: select it, press D and walk the agent to its goal. ${RULE}`;
      },
      done: (e) => e.kind === "move" && e.modeBefore === "demonstrate" && e.outcome.episode_ended === "goal"
        && notShown(e.state, env).length === 0,
    },
    {
      id: "ready",
      title: "You are ready",
      text: `That is all. In the study you teach ${agents} agent${agents === 1 ? "" : "s"} like this, one at a time, and cannot go back to an earlier one. Teach each one as well as you can, then press Next (N). Press N now to begin.`,
      done: () => false,
    },
  ];
}

export class Tutorial {
  constructor(teacher) {
    this.teacher = teacher;
    this.steps = steps(teacher);
    this.index = Math.min(teacher.participant.tutorial_step ?? 0, this.steps.length - 1);
    this.counters = {};
    this.skipSatisfied();
    teacher.on((event) => this.observe(event));
    teacher.tutorialCard.hidden = false;
  }

  get complete() {
    return this.index >= this.steps.length - 1;
  }

  save() {
    const step = this.index;
    this.teacher.participant.tutorial_step = step;
    this.teacher.seq.post("/api/participant/tutorial", () => (this.teacher.closed ? null : { step }))
      .catch((error) => console.warn("could not keep the tutorial's step", error));
  }

  skipSatisfied() {
    while (!this.complete && this.steps[this.index].already?.(this.teacher.t)) this.index += 1;
  }

  observe(event) {
    if (this.complete) return;
    const step = this.steps[this.index];
    if (step.done(event, this.counters)) {
      this.index += 1;
      this.counters = {};
      this.skipSatisfied();
      this.save();
      this.teacher.update();
      this.card?.classList.add("advanced");
    }
  }

  render() {
    const step = this.steps[this.index];
    const total = this.steps.length;
    const bar = h("div", { class: "tutorial-bar", "aria-hidden": "true" },
      h("div", { class: "tutorial-bar-fill", style: `width: ${Math.round((100 * this.index) / (total - 1))}%` }));
    this.card = this.teacher.tutorialCard;
    this.card.dataset.step = step.id;
    this.card.replaceChildren(
      h("p", { class: "tutorial-count" }, `Tutorial step ${this.index + 1} of ${total}`),
      bar,
      h("h2", {}, step.title),
      h("p", {}, typeof step.text === "function" ? step.text(this.teacher.t) : step.text));
  }
}
