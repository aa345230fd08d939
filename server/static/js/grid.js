// Drawing of a grid world (SVG, scaled to its box): terrain, walls, machines, gravity colours,
// the tasks' goals or fields, and the agent. Shared by the participant's page and the
// dashboard's replay. Every colour has a pattern, a letter or a label beside it.
//
// The built-in terrains, machines and gravity colours have their own patterns and pictures
// below. A study's own (the environment's ``drawing``, from the server) are drawn in their
// colour: a terrain or gravity colour with one of OWN_PATTERNS and its initial on every cell, a
// machine as a generic machine with its initial and its name.

const NS = "http://www.w3.org/2000/svg";
const C = 100; // one cell in SVG units
let uid = 0;

export function svg(name, attrs = {}, parent = null) {
  const node = document.createElementNS(NS, name);
  for (const [key, value] of Object.entries(attrs)) {
    if (value !== null && value !== undefined) node.setAttribute(key, String(value));
  }
  if (parent) parent.appendChild(node);
  return node;
}

function text(parent, content, attrs) {
  const node = svg("text", attrs, parent);
  node.textContent = content;
  return node;
}

export const TERRAIN = {
  floor: { fill: "#f7f5f0", label: "Floor" },
  dirt: { fill: "#ecdcbc", label: "Dirt: free" },
  soil: { fill: "#9a6a3f", label: "Soil: needs the plow" },
  grass: { fill: "#a8d88f", label: "Grass: needs the sprinkler" },
  crops: { fill: "#e6bb45", label: "Crops: need the harvester" },
};
export const GRAVITY_COLOURS = {
  orange: { fill: "#E69F00", letter: "O" },
  green: { fill: "#009E73", letter: "G" },
  purple: { fill: "#CC79A7", letter: "P" },
};
export const MACHINES = {
  plow: "Plow",
  sprinkler: "Sprinkler",
  harvester: "Harvester",
};
const ARROW_ANGLE = { north: 0, east: 90, south: 180, west: 270 };
const CANNOT = { north: "down", south: "up", east: "left", west: "right" };

/** A gravity colour's letter: the built-in one, or a study's own colour's initial. */
export function colourLetter(env, colour) {
  return GRAVITY_COLOURS[colour]?.letter ?? ownKind(env, "colour", colour)?.initial ?? "?";
}

export function gravityRule(direction) {
  return `gravity ${direction}: cannot move ${CANNOT[direction] ?? "?"}`;
}

/** The agent's cell and feature from a state index (as Environment.describe_state does). */
export function decodeState(env, state) {
  const features = env.features.length;
  const cell = Math.floor(state / features);
  const feature = env.features[state % features];
  const described = { state, row: Math.floor(cell / env.width), column: cell % env.width };
  if (env.domain === "farming") described.carrying = feature;
  if (env.domain === "gravity") described.gravity = feature;
  return described;
}

/** A name as one CSS class word ("sky blue" -> "sky-blue"). */
function slug(name) {
  return String(name).replace(/\s+/g, "-");
}

/** A study's own kind's initial: its first letter, or its first two when that letter is taken
 * (by a built-in gravity colour's letter or an earlier kind). */
function initialOf(name, used) {
  const letters = name.replace(/[^a-z]/gi, "");
  const one = letters.slice(0, 1).toUpperCase();
  const two = one + letters.slice(1, 2).toLowerCase();
  for (const candidate of [one, two]) {
    if (candidate && !used.has(candidate)) {
      used.add(candidate);
      return candidate;
    }
  }
  for (let n = 2; ; n++) {
    if (!used.has(`${one}${n}`)) {
      used.add(`${one}${n}`);
      return `${one}${n}`;
    }
  }
}

const KINDS = new WeakMap();

/** The environment's kinds (its ``drawing``: terrains, machines and gravity colours), by
 * ``terrain:NAME``, ``machine:NAME`` and ``colour:NAME``: {name, label, colour, built_in}, and
 * for a study's own kind its initial and (terrains and colours) the number of its pattern. */
export function kindsOf(env) {
  if (!env || typeof env !== "object") return new Map();
  let kinds = KINDS.get(env);
  if (kinds) return kinds;
  kinds = new Map();
  const used = new Set(Object.values(GRAVITY_COLOURS).map((c) => c.letter));
  let own = 0;
  const drawing = env.drawing ?? {};
  for (const [category, list] of [["terrain", drawing.terrains], ["colour", drawing.colours], ["machine", drawing.machines]]) {
    for (const kind of list ?? []) {
      const entry = { ...kind, category };
      if (!kind.built_in) {
        entry.initial = initialOf(kind.name, used);
        if (category !== "machine") entry.pattern = own++;
      }
      kinds.set(`${category}:${kind.name}`, entry);
    }
  }
  KINDS.set(env, kinds);
  return kinds;
}

/** A study's own kind (null for a built-in one or one the environment does not describe). */
export function ownKind(env, category, name) {
  const kind = kindsOf(env).get(`${category}:${name}`);
  return kind && !kind.built_in ? kind : null;
}

/** A terrain's, machine's or gravity colour's name for people ("Vines", "Plow"). */
export function kindLabel(env, category, name) {
  const kind = kindsOf(env).get(`${category}:${name}`);
  if (kind) return kind.label;
  if (category === "machine" && MACHINES[name]) return MACHINES[name];
  return name.charAt(0).toUpperCase() + name.slice(1);
}

/** ``hex`` darkened (factor < 1) or lightened towards white (factor > 1). */
function shade(hex, factor) {
  const channels = [1, 3, 5].map((i) => parseInt(hex.slice(i, i + 2), 16));
  const mixed = channels.map((v) => Math.round(factor < 1 ? v * factor : v + (255 - v) * (factor - 1)));
  return `#${mixed.map((v) => Math.max(0, Math.min(255, v)).toString(16).padStart(2, "0")).join("")}`;
}

function luminance(hex) {
  const [r, g, b] = [1, 3, 5].map((i) => parseInt(hex.slice(i, i + 2), 16) / 255);
  return 0.2126 * r + 0.7152 * g + 0.0722 * b;
}

/** The marks over a study's own colour, one per pattern number (then again from the first),
 * none like the built-in ones: a cross-hatch, stripes, a checker, a zigzag, rings. */
const OWN_PATTERNS = [
  (p, ink) => svg("path", { d: "M0 0 L20 20 M20 0 L0 20", stroke: ink, "stroke-width": 2.5 }, p),
  (p, ink) => svg("path", { d: "M5 0 V20 M15 0 V20", stroke: ink, "stroke-width": 3 }, p),
  (p, ink) => {
    svg("rect", { width: 10, height: 10, fill: ink }, p);
    svg("rect", { x: 10, y: 10, width: 10, height: 10, fill: ink }, p);
  },
  (p, ink) => svg("path", { d: "M0 15 L5 5 L10 15 L15 5 L20 15", stroke: ink, "stroke-width": 2.5, fill: "none" }, p),
  (p, ink) => svg("circle", { cx: 10, cy: 10, r: 5, stroke: ink, "stroke-width": 2.5, fill: "none" }, p),
];

function ownPatterns(defs, prefix, env) {
  for (const kind of kindsOf(env).values()) {
    if (kind.pattern === undefined) continue;
    const p = svg("pattern", { id: `${prefix}-own-${kind.pattern}`, width: 20, height: 20, patternUnits: "userSpaceOnUse", "data-kind": kind.name }, defs);
    svg("rect", { width: 20, height: 20, fill: kind.colour }, p);
    const ink = luminance(kind.colour) < 0.25 ? shade(kind.colour, 1.45) : shade(kind.colour, 0.7);
    const mark = svg("g", { opacity: 0.75 }, p);
    OWN_PATTERNS[kind.pattern % OWN_PATTERNS.length](mark, ink);
  }
}

/** A study's own kind's initial in a white disc at (cx, cy). */
function initialBadge(parent, kind, cx, cy, r) {
  const g = svg("g", { class: "kind-initial" }, parent);
  svg("circle", { cx, cy, r, fill: "#fff", stroke: "#1f2328", "stroke-width": r / 6 }, g);
  const size = kind.initial.length > 1 ? r * 1.05 : r * 1.3;
  text(g, kind.initial, { x: cx, y: cy + 1, "text-anchor": "middle", "dominant-baseline": "central", "font-size": size, "font-weight": 700, fill: "#1f2328" });
  return g;
}

function patterns(defs, prefix, env = null) {
  const make = (id, build) => {
    const p = svg("pattern", { id: `${prefix}-${id}`, width: 20, height: 20, patternUnits: "userSpaceOnUse" }, defs);
    build(p);
  };
  make("wall", (p) => {
    svg("rect", { width: 20, height: 20, fill: "#2f3542" }, p);
    svg("path", { d: "M-5 5 L5 -5 M0 20 L20 0 M15 25 L25 15", stroke: "#566074", "stroke-width": 4 }, p);
  });
  make("soil", (p) => {
    svg("rect", { width: 20, height: 20, fill: TERRAIN.soil.fill }, p);
    svg("path", { d: "M0 6 H20 M0 16 H20", stroke: "#6f4626", "stroke-width": 3 }, p);
  });
  make("grass", (p) => {
    svg("rect", { width: 20, height: 20, fill: TERRAIN.grass.fill }, p);
    svg("path", { d: "M5 15 L5 9 M8 15 L10 8 M15 6 L15 0 M18 6 L20 -1", stroke: "#3f8a2c", "stroke-width": 2, "stroke-linecap": "round" }, p);
  });
  make("crops", (p) => {
    svg("rect", { width: 20, height: 20, fill: TERRAIN.crops.fill }, p);
    svg("path", { d: "M5 17 V5 M2 8 L5 5 L8 8 M2 12 L5 9 L8 12 M15 17 V5 M12 8 L15 5 L18 8 M12 12 L15 9 L18 12", stroke: "#8d6208", "stroke-width": 1.8, fill: "none" }, p);
  });
  make("dirt", (p) => {
    svg("rect", { width: 20, height: 20, fill: TERRAIN.dirt.fill }, p);
    svg("circle", { cx: 5, cy: 6, r: 1.2, fill: "#c9b48c" }, p);
    svg("circle", { cx: 15, cy: 15, r: 1.2, fill: "#c9b48c" }, p);
  });
  make("orange", (p) => {
    svg("rect", { width: 20, height: 20, fill: GRAVITY_COLOURS.orange.fill }, p);
    svg("path", { d: "M-5 5 L5 -5 M0 20 L20 0 M15 25 L25 15", stroke: "#b87d00", "stroke-width": 3 }, p);
  });
  make("green", (p) => {
    svg("rect", { width: 20, height: 20, fill: GRAVITY_COLOURS.green.fill }, p);
    svg("circle", { cx: 5, cy: 5, r: 2.5, fill: "#006b4e" }, p);
    svg("circle", { cx: 15, cy: 15, r: 2.5, fill: "#006b4e" }, p);
  });
  make("purple", (p) => {
    svg("rect", { width: 20, height: 20, fill: GRAVITY_COLOURS.purple.fill }, p);
    svg("path", { d: "M0 10 H20 M10 0 V20", stroke: "#a6568a", "stroke-width": 2.5 }, p);
  });
  ownPatterns(defs, prefix, env);
}

/** The fill of a terrain's cell, or (``category`` "colour") of a gravity colour's. */
export function fillOf(prefix, terrain, env = null, category = "terrain") {
  const own = ownKind(env, category, terrain);
  if (own) return `url(#${prefix}-own-${own.pattern})`;
  if (terrain === "floor") return TERRAIN.floor.fill;
  return `url(#${prefix}-${terrain})`;
}

/** A machine's picture in a 100x100 box (a study's own machine: a generic machine in its
 * colour with its initial). */
export function machineIcon(parent, machine, env = null) {
  const own = ownKind(env, "machine", machine);
  const g = svg("g", { class: `machine-icon machine-${own ? "own" : machine}`, "data-machine": machine }, parent);
  if (own) {
    // A tractor-like body with an arm and a tool, two wheels, and the initial on the body.
    const ink = "#1f2328";
    svg("path", { d: "M12 30 L30 22 L34 30", stroke: ink, "stroke-width": 5, fill: "none", "stroke-linecap": "round", "stroke-linejoin": "round" }, g);
    svg("rect", { x: 26, y: 30, width: 62, height: 38, rx: 6, fill: own.colour, stroke: ink, "stroke-width": 4, class: "machine-body" }, g);
    svg("rect", { x: 6, y: 50, width: 20, height: 14, rx: 3, fill: own.colour, stroke: ink, "stroke-width": 4 }, g);
    svg("circle", { cx: 40, cy: 76, r: 11, fill: "#3d434c", stroke: ink, "stroke-width": 4 }, g);
    svg("circle", { cx: 76, cy: 76, r: 11, fill: "#3d434c", stroke: ink, "stroke-width": 4 }, g);
    initialBadge(g, own, 57, 48, 15);
    return g;
  }
  if (machine === "plow") {
    svg("path", { d: "M30 18 L56 58", stroke: "#7a4a22", "stroke-width": 8, "stroke-linecap": "round" }, g);
    svg("path", { d: "M22 18 H40", stroke: "#7a4a22", "stroke-width": 8, "stroke-linecap": "round" }, g);
    svg("path", { d: "M40 56 L82 52 Q80 74 60 80 L36 78 Z", fill: "#6b7785", stroke: "#1f2328", "stroke-width": 4, "stroke-linejoin": "round" }, g);
  } else if (machine === "sprinkler") {
    svg("rect", { x: 44, y: 46, width: 12, height: 36, rx: 3, fill: "#6b7785", stroke: "#1f2328", "stroke-width": 4 }, g);
    svg("rect", { x: 30, y: 78, width: 40, height: 10, rx: 4, fill: "#6b7785", stroke: "#1f2328", "stroke-width": 4 }, g);
    svg("circle", { cx: 50, cy: 42, r: 9, fill: "#0072B2", stroke: "#1f2328", "stroke-width": 4 }, g);
    for (const [x, y] of [[22, 30], [50, 12], [78, 30]]) {
      svg("path", { d: `M${x} ${y - 9} Q${x + 8} ${y + 3} ${x} ${y + 7} Q${x - 8} ${y + 3} ${x} ${y - 9} Z`, fill: "#56B4E9", stroke: "#0072B2", "stroke-width": 3 }, g);
    }
  } else if (machine === "harvester") {
    svg("rect", { x: 34, y: 30, width: 46, height: 36, rx: 5, fill: "#F0E442", stroke: "#1f2328", "stroke-width": 4 }, g);
    svg("rect", { x: 56, y: 16, width: 20, height: 18, rx: 3, fill: "#bfe3f5", stroke: "#1f2328", "stroke-width": 4 }, g);
    svg("path", { d: "M14 34 V66 M14 38 H34 M14 50 H34 M14 62 H34", stroke: "#1f2328", "stroke-width": 5, "stroke-linecap": "round" }, g);
    svg("circle", { cx: 46, cy: 72, r: 12, fill: "#3d434c", stroke: "#1f2328", "stroke-width": 4 }, g);
    svg("circle", { cx: 72, cy: 74, r: 9, fill: "#3d434c", stroke: "#1f2328", "stroke-width": 4 }, g);
  }
  return g;
}

function arrow(parent, direction, attrs = {}) {
  const g = svg("g", { transform: `rotate(${ARROW_ANGLE[direction] ?? 0} 50 50)`, ...attrs }, parent);
  svg("path", { d: "M50 14 L76 46 H60 V84 H40 V46 H24 Z", fill: "#ffffff", stroke: "#1f2328", "stroke-width": 6, "stroke-linejoin": "round" }, g);
  return g;
}

/** The agent's picture (a small robot) in a 100x100 box. */
export function robotIcon(parent, colour) {
  const g = svg("g", { class: "robot" }, parent);
  svg("line", { x1: 50, y1: 26, x2: 50, y2: 13, stroke: "#1f2328", "stroke-width": 5, "stroke-linecap": "round" }, g);
  svg("circle", { cx: 50, cy: 11, r: 6, fill: colour, stroke: "#1f2328", "stroke-width": 3.5, class: "robot-fill" }, g);
  svg("rect", { x: 17, y: 26, width: 66, height: 58, rx: 15, fill: colour, stroke: "#1f2328", "stroke-width": 5, class: "robot-fill" }, g);
  for (const x of [37, 63]) {
    svg("circle", { cx: x, cy: 51, r: 10, fill: "#fff", stroke: "#1f2328", "stroke-width": 3.5 }, g);
    svg("circle", { cx: x, cy: 52, r: 4.2, fill: "#1f2328" }, g);
  }
  svg("rect", { x: 37, y: 68, width: 26, height: 7, rx: 3.5, fill: "#fff", stroke: "#1f2328", "stroke-width": 3 }, g);
  return g;
}

function boundingBox(cells) {
  const rows = cells.map((c) => c[0]);
  const columns = cells.map((c) => c[1]);
  const box = { r0: Math.min(...rows), r1: Math.max(...rows), c0: Math.min(...columns), c1: Math.max(...columns) };
  box.rect = (box.r1 - box.r0 + 1) * (box.c1 - box.c0 + 1) === cells.length;
  return box;
}

export class GridView {
  /**
   * @param {HTMLElement} container  the box the drawing fills (keeps the grid's aspect ratio)
   * @param {object} env             Environment.describe() from the server
   * @param {object} options         {reveal: show gravity directions}
   */
  constructor(container, env, options = {}) {
    this.env = env;
    this.reveal = Boolean(options.reveal && env.gravity_of_colour);
    this.prefix = `g${++uid}`;
    this.task = 0;
    this.container = container;
    container.classList.add("grid-box");
    container.style.setProperty("--ratio", `${env.width / env.height}`);
    this.root = svg("svg", {
      viewBox: `0 0 ${env.width * C} ${env.height * C}`,
      class: `grid grid-${env.domain}`,
      role: "img",
      "aria-label": options.label ?? `Grid world ${env.name}, ${env.width} by ${env.height} cells`,
      "data-environment": env.name,
    });
    container.appendChild(this.root);
    const defs = svg("defs", {}, this.root);
    patterns(defs, this.prefix, env);
    this.drawTerrain();
    this.goalLayer = svg("g", { class: "goals" }, this.root);
    this.drawGoals();
    this.drawMachines();
    this.agent = svg("g", { class: "agent", "data-row": -1, "data-column": -1 }, this.root);
    this.agentInner = svg("g", {}, this.agent);
    this.robot = robotIcon(this.agentInner, "#888");
    this.badge = svg("g", { class: "agent-badge" }, this.agentInner);
    this.bumpMark = svg("rect", { class: "bump-mark", "aria-hidden": "true" }, this.agent);
    this.bumps = 0;
  }

  /** A move towards ``direction`` (UP, DOWN, LEFT, RIGHT) that left the agent where it was: it
   * nudges that way and back, and a red bar on that side of its cell shows where it stopped. */
  bump(direction) {
    const edge = { UP: [8, 0, 84, 9], DOWN: [8, 91, 84, 9], LEFT: [0, 8, 9, 84], RIGHT: [91, 8, 9, 84] }[direction];
    if (!edge) return;
    const [x, y, width, height] = edge;
    for (const [name, value] of Object.entries({ x, y, width, height })) this.bumpMark.setAttribute(name, value);
    this.bumps += 1;
    this.agent.dataset.bumps = this.bumps;
    this.agent.dataset.bump = direction.toLowerCase();
    for (const node of [this.agentInner, this.bumpMark]) {
      node.classList.remove("on");
      void node.getBoundingClientRect(); // restart the animation
      node.classList.add("on");
    }
    clearTimeout(this.bumpTimer);
    this.bumpTimer = setTimeout(() => {
      this.agentInner.classList.remove("on");
      this.bumpMark.classList.remove("on");
    }, 700);
  }

  drawTerrain() {
    const { env, prefix } = this;
    const layer = svg("g", { class: "terrain" }, this.root);
    const walls = new Set((env.walls ?? []).map(([r, c]) => `${r},${c}`));
    const initials = [];
    for (let r = 0; r < env.height; r++) {
      for (let c = 0; c < env.width; c++) {
        const terrain = walls.has(`${r},${c}`) ? "wall" : env.terrain?.[r]?.[c] ?? "floor";
        const cell = svg("rect", {
          x: c * C, y: r * C, width: C, height: C,
          fill: terrain === "wall" ? `url(#${prefix}-wall)` : fillOf(prefix, terrain, env),
          class: `cell cell-${slug(terrain)}`,
        }, layer);
        const own = ownKind(env, "terrain", terrain);
        if (own) {
          cell.classList.add("cell-own");
          cell.dataset.terrain = terrain;
          cell.dataset.colour = own.colour;
          svg("title", {}, cell).textContent = own.label;
          initials.push([r, c, own]);
        }
      }
    }
    // Cell borders: a light grid over everything but walls.
    const lines = [];
    for (let r = 1; r < env.height; r++) lines.push(`M0 ${r * C} H${env.width * C}`);
    for (let c = 1; c < env.width; c++) lines.push(`M${c * C} 0 V${env.height * C}`);
    svg("path", { d: lines.join(" "), stroke: "rgba(31,35,40,0.14)", "stroke-width": 2, fill: "none" }, layer);
    // A study's own terrain: its initial on each of its cells.
    for (const [r, c, own] of initials) {
      initialBadge(svg("g", { transform: `translate(${c * C} ${r * C})`, class: "cell-initial", "data-terrain": own.name }, layer), own, 22, 22, 15);
    }
    for (const { row, column, colour } of env.colours ?? []) {
      const direction = this.reveal ? env.gravity_of_colour[colour] : null;
      const g = svg("g", {
        transform: `translate(${column * C} ${row * C})`,
        class: `gravity-cell gravity-${slug(colour)}`,
        "data-direction": direction,
      }, layer);
      const own = ownKind(env, "colour", colour);
      if (own) g.dataset.colour = own.colour;
      svg("title", {}, g).textContent = `${colour} cell${direction ? `: sets the gravity ${direction}` : ""}`;
      svg("rect", { x: 4, y: 4, width: C - 8, height: C - 8, rx: 10, fill: fillOf(prefix, colour, env, "colour"), stroke: "#1f2328", "stroke-width": 4 }, g);
      if (direction) {
        arrow(g, direction, { transform: `translate(20 20) scale(0.6) rotate(${ARROW_ANGLE[direction]} 50 50)` });
      } else {
        svg("circle", { cx: 50, cy: 50, r: 22, fill: "#fff", stroke: "#1f2328", "stroke-width": 4 }, g);
        text(g, colourLetter(env, colour), { x: 50, y: 51, "text-anchor": "middle", "dominant-baseline": "central", "font-size": 30, "font-weight": 700, fill: "#1f2328" });
      }
    }
    // Outline the grid.
    svg("rect", { x: 1.5, y: 1.5, width: env.width * C - 3, height: env.height * C - 3, fill: "none", stroke: "#1f2328", "stroke-width": 3 }, layer);
  }

  drawGoals() {
    const { env } = this;
    this.goalLayer.replaceChildren();
    env.tasks.forEach((task, index) => {
      const selected = index === this.task;
      const g = svg("g", { class: `goal ${selected ? "goal-selected" : "goal-other"}`, "data-task": index }, this.goalLayer);
      const box = boundingBox(task.goal_cells);
      if (box.rect && task.goal_cells.length > 1) {
        // A field: one outline around it and its name on a tab.
        const x = box.c0 * C, y = box.r0 * C;
        const w = (box.c1 - box.c0 + 1) * C, h = (box.r1 - box.r0 + 1) * C;
        svg("rect", { x: x + 4, y: y + 4, width: w - 8, height: h - 8, rx: 8, fill: "none", class: "goal-outline" }, g);
        const above = box.r0 > 0;
        const label = task.name;
        const tabWidth = Math.max(w, label.length * 19 + 40);
        const tabX = Math.min(Math.max(0, x + w / 2 - tabWidth / 2), env.width * C - tabWidth);
        const tabY = above ? y - 44 : y + h + 6;
        svg("rect", { x: tabX, y: tabY, width: tabWidth, height: 38, rx: 8, class: "goal-tab" }, g);
        text(g, selected ? `★ ${label}` : label, { x: tabX + tabWidth / 2, y: tabY + 20, "text-anchor": "middle", "dominant-baseline": "central", "font-size": 26, "font-weight": 700, class: "goal-label" });
      } else {
        for (const [r, c] of task.goal_cells) {
          const cell = svg("g", { transform: `translate(${c * C} ${r * C})` }, g);
          svg("rect", { x: 6, y: 6, width: C - 12, height: C - 12, rx: 12, class: "goal-outline goal-cell" }, cell);
          if (selected) {
            svg("path", { d: starPath(50, 34, 17, 7.5), class: "goal-star" }, cell);
          }
          const long = task.name.length > 2;
          text(cell, task.name, {
            x: 50, y: selected ? 72 : 52, "text-anchor": "middle", "dominant-baseline": "central",
            "font-size": long ? 22 : 36, "font-weight": 700, class: "goal-label",
            ...(task.name.length > 5 ? { textLength: 78, lengthAdjust: "spacingAndGlyphs" } : {}),
          });
        }
      }
    });
    // The selected task on top.
    const chosen = this.goalLayer.querySelector(".goal-selected");
    if (chosen) this.goalLayer.appendChild(chosen);
  }

  drawMachines() {
    const layer = svg("g", { class: "machines" }, this.root);
    for (const { row, column, machine } of this.env.machines ?? []) {
      const g = svg("g", { transform: `translate(${column * C} ${row * C})`, class: "machine", "data-machine": machine }, layer);
      const own = ownKind(this.env, "machine", machine);
      if (own) {
        g.dataset.colour = own.colour;
        svg("title", {}, g).textContent = own.label;
      }
      svg("rect", { x: 5, y: 5, width: C - 10, height: C - 10, rx: 12, fill: "#ffffff", stroke: "#1f2328", "stroke-width": 3 }, g);
      machineIcon(svg("g", { transform: "translate(18 6) scale(0.64)" }, g), machine, this.env);
      const name = own ? own.label : MACHINES[machine] ?? machine;
      text(g, name, { x: 50, y: 86, "text-anchor": "middle", "font-size": 17, "font-weight": 700, fill: "#1f2328", ...(name.length > 6 ? { textLength: 80, lengthAdjust: "spacingAndGlyphs" } : {}) });
    }
  }

  setTask(index) {
    if (index === this.task) return;
    this.task = index;
    this.drawGoals();
  }

  /** The agent at ``agent`` ({row, column, carrying?, gravity?}) in ``colour``. */
  setAgent(agent, colour) {
    if (!agent) {
      this.agent.style.display = "none";
      return;
    }
    this.agent.style.display = "";
    this.agent.style.transform = `translate(${agent.column * C}px, ${agent.row * C}px)`;
    this.agent.dataset.row = agent.row;
    this.agent.dataset.column = agent.column;
    this.agent.dataset.state = agent.state;
    for (const part of this.robot.querySelectorAll(".robot-fill")) part.setAttribute("fill", colour);
    const feature = agent.carrying ?? agent.gravity ?? "";
    this.agent.dataset.feature = feature;
    if (this.badgeFeature !== feature) {
      this.badgeFeature = feature;
      this.badge.replaceChildren();
      if (agent.carrying && agent.carrying !== "none") {
        svg("circle", { cx: 80, cy: 80, r: 22, fill: "#fff", stroke: "#1f2328", "stroke-width": 4 }, this.badge);
        machineIcon(svg("g", { transform: "translate(61 61) scale(0.38)" }, this.badge), agent.carrying, this.env);
      } else if (agent.gravity) {
        const g = svg("g", { transform: "translate(56 56) scale(0.46)" }, this.badge);
        svg("circle", { cx: 50, cy: 50, r: 48, fill: "#1f2328" }, g);
        arrow(g, agent.gravity, { transform: `translate(10 10) scale(0.8) rotate(${ARROW_ANGLE[agent.gravity]} 50 50)` });
      }
    }
  }
}

export function starPath(cx, cy, outer, inner) {
  const points = [];
  for (let i = 0; i < 10; i++) {
    const radius = i % 2 === 0 ? outer : inner;
    const angle = (Math.PI / 5) * i - Math.PI / 2;
    points.push(`${(cx + radius * Math.cos(angle)).toFixed(1)} ${(cy + radius * Math.sin(angle)).toFixed(1)}`);
  }
  return `M${points.join(" L")} Z`;
}

/** A small legend swatch (an inline SVG of one cell); ``env`` describes a study's own kinds. */
export function swatch(kind, value, env = null) {
  const prefix = `s${++uid}`;
  const root = svg("svg", { viewBox: "0 0 100 100", class: "swatch", "aria-hidden": "true", "data-kind": value });
  patterns(svg("defs", {}, root), prefix, env);
  if (kind === "terrain") {
    svg("rect", { width: 100, height: 100, fill: value === "wall" ? `url(#${prefix}-wall)` : fillOf(prefix, value, env), stroke: "#1f2328", "stroke-width": 6 }, root);
    const own = ownKind(env, "terrain", value);
    if (own) initialBadge(root, own, 50, 50, 26);
  } else if (kind === "machine") {
    svg("rect", { width: 100, height: 100, rx: 14, fill: "#fff", stroke: "#1f2328", "stroke-width": 6 }, root);
    machineIcon(svg("g", { transform: "translate(8 8) scale(0.84)" }, root), value, env);
  } else if (kind === "colour") {
    svg("rect", { width: 100, height: 100, rx: 14, fill: fillOf(prefix, value, env, "colour"), stroke: "#1f2328", "stroke-width": 6 }, root);
    svg("circle", { cx: 50, cy: 50, r: 24, fill: "#fff", stroke: "#1f2328", "stroke-width": 4 }, root);
    text(root, colourLetter(env, value), { x: 50, y: 52, "text-anchor": "middle", "dominant-baseline": "central", "font-size": 32, "font-weight": 700 });
  } else if (kind === "goal") {
    svg("rect", { width: 100, height: 100, fill: TERRAIN.floor.fill }, root);
    svg("rect", { x: 8, y: 8, width: 84, height: 84, rx: 12, class: "goal-outline legend-goal" }, root);
    svg("path", { d: starPath(50, 50, 26, 11), class: "goal-star" }, root);
  } else if (kind === "gravity") {
    svg("circle", { cx: 50, cy: 50, r: 48, fill: "#1f2328" }, root);
    arrow(root, value, { transform: `translate(10 10) scale(0.8) rotate(${ARROW_ANGLE[value]} 50 50)` });
  }
  return root;
}
