// The instructional attention check between two agents: "move the robot to the star using the
// arrow keys" on a small open grid. The server moves the robot and decides when the check is
// over (the star reached, or the moves allowed used up); the page shows what it answers, so a
// reload continues here, and it never tells the participant they failed: it says their moves
// are recorded and goes on.

import { h } from "./dom.js";
import { robotIcon, starPath, svg } from "./grid.js";

const KEYS = { ArrowUp: "UP", ArrowDown: "DOWN", ArrowLeft: "LEFT", ArrowRight: "RIGHT" };
const BUTTONS = [
  ["UP", "↑", "Up"],
  ["LEFT", "←", "Left"],
  ["DOWN", "↓", "Down"],
  ["RIGHT", "→", "Right"],
];
const MAX_QUEUED_MOVES = 2; // arrow presses waiting for the server (key repeat is dropped)
const CELL = 100;
const ROBOT_COLOUR = "#f2c14e";

export class AttentionCheck {
  /**
   * @param {object} options  {root, check (AttentionCheckView), post(url, body) -> answer or
   *                           null, onDone()}
   */
  constructor(options) {
    Object.assign(this, options);
    this.closed = false;
    this.queued = 0;
    this.onKey = (event) => this.key(event);
  }

  start() {
    this.render();
    document.addEventListener("keydown", this.onKey);
  }

  close() {
    this.closed = true;
    document.removeEventListener("keydown", this.onKey);
  }

  render() {
    const n = this.check.size;
    this.board = svg("svg", { viewBox: `0 0 ${n * CELL} ${n * CELL}`, class: "check-board", role: "img" });
    for (let r = 0; r < n; r++) {
      for (let c = 0; c < n; c++) {
        svg("rect", { x: c * CELL + 2, y: r * CELL + 2, width: CELL - 4, height: CELL - 4, rx: 10, class: "check-cell" }, this.board);
      }
    }
    const [sr, sc] = this.check.star;
    svg("path", { d: starPath(sc * CELL + 50, sr * CELL + 50, 34, 15), class: "check-star", "data-testid": "check-star" }, this.board);
    this.robot = svg("g", { class: "check-robot", "data-testid": "check-robot" }, this.board);
    robotIcon(this.robot, ROBOT_COLOUR);
    this.status = h("p", { class: "check-status", role: "status", "aria-live": "polite" });
    this.pad = h("div", { class: "check-pad", role: "group", "aria-label": "Move the robot" },
      BUTTONS.map(([action, arrow, label]) => h("button", {
        type: "button", class: `btn check-arrow check-${action.toLowerCase()}`, "data-move": action,
        "aria-label": label, onclick: () => this.move(action),
      }, h("span", { "aria-hidden": "true" }, arrow))));
    // Shown once the check is over.
    this.continueButton = h("button", { class: "btn primary big", type: "button", "data-action": "after-check", onclick: () => this.done() },
      h("kbd", {}, "Enter"), "Continue");
    this.actions = h("div", { class: "actions" });
    this.root.replaceChildren(h("main", { class: "sheet attention-check", "data-testid": "attention-check" },
      h("p", { class: "eyebrow" }, this.check.of > 1 ? `A short check (${this.check.number} of ${this.check.of})` : "A short check"),
      h("h1", {}, "Move the robot to the star using the arrow keys"),
      h("p", {}, "Before the next agent: use the arrow keys (or the arrow buttons by the grid) to move the robot onto the star."),
      h("div", { class: "check-stage" }, this.board, this.pad),
      this.status,
      this.actions));
    const heading = this.root.querySelector("h1");
    heading.setAttribute("tabindex", "-1");
    heading.focus({ preventScroll: true });
    this.draw();
  }

  draw() {
    const { robot, star, size, moves_made: made, moves_allowed: allowed, status } = this.check;
    this.robot.setAttribute("transform", `translate(${robot[1] * CELL + 10} ${robot[0] * CELL + 10}) scale(0.8)`);
    this.board.setAttribute("aria-label",
      `A ${size} by ${size} grid: the robot is in row ${robot[0] + 1}, column ${robot[1] + 1}; the star is in row ${star[0] + 1}, column ${star[1] + 1}.`);
    this.root.querySelector(".attention-check").dataset.status = status;
    if (status === "active") {
      const left = allowed - made;
      this.status.textContent = `${left} ${left === 1 ? "move" : "moves"} left.`;
      return;
    }
    this.status.textContent = status === "passed"
      ? "The robot reached the star. Thank you: this is recorded. Continue to the next agent."
      : "That was the last move. Thank you: this is recorded. Continue to the next agent.";
    for (const button of this.pad.querySelectorAll("button")) button.disabled = true;
    this.actions.replaceChildren(this.continueButton);
    this.continueButton.focus();
  }

  async move(action) {
    if (this.closed || this.check.status !== "active" || this.queued >= MAX_QUEUED_MOVES) return;
    this.queued += 1;
    try {
      const answer = await this.post("/api/participant/attention-check/move", () =>
        (this.closed || this.check.status !== "active" ? null : { action }));
      if (!answer || this.closed) return;
      // Answers come in order: each is the check after its move.
      this.check = answer.check;
      this.draw();
    } finally {
      this.queued -= 1;
    }
  }

  done() {
    if (this.closed) return;
    this.close();
    this.onDone();
  }

  key(event) {
    if (this.closed || event.ctrlKey || event.metaKey || event.altKey) return;
    if (document.querySelector("dialog[open]")) return; // the withdrawal's
    if (KEYS[event.key]) {
      event.preventDefault(); // never scroll the page
      if (!event.repeat || this.queued === 0) this.move(KEYS[event.key]);
    }
  }
}
