"""Our environments as Gymnasium environments: the same tasks on the same true dynamics.

Everything comes from the domain objects (``server.domains.make``): the states, the true
transition table (sampled, stochastic where it is), each task's start distribution and goal,
the horizon, and the layout the page draws. One episode is one task: ``reset`` takes
``options={"task": k}`` (else a task drawn at random), starts from that task's start
distribution and the episode is truncated after the environment's horizon of steps (our
environments have no terminal state: the agent may stay on the goal, and every step it spends
there counts).

The reward of a step is the task's reward (1 on its goal, 0 elsewhere) counted as the exact
evaluation (``server.learners.evaluation``) counts it, so that a policy's expected episode
return here is our exact return of that policy. See ``step_reward``.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from server import domains
from server.domains import drawing, farming, gravity, navigation
from server.domains.base import Environment

NAMESPACE = "BAMStudy"
VERSION = 0
# Each registered environment's Gymnasium name (its id is NAMESPACE/NAME-vVERSION).
GYMNASIUM_NAMES: dict[str, str] = {
    name: "".join(part.capitalize() for part in name.split("-")) for name in domains.NAMES
}
OBSERVATIONS = ("state", "grid")
CELL_PIXELS = 16


# The ids of the study environments registered with Gymnasium, by environment name.
_STUDY_IDS: dict[str, str] = {}


def environment_id(name: str) -> str:
    """The Gymnasium id of one of our environments (``BAMStudy/Doorway-v0``), or of a study's
    own registered with ``register_study_environments``."""
    if name in _STUDY_IDS:
        return _STUDY_IDS[name]
    if name not in GYMNASIUM_NAMES:
        raise ValueError(f"unknown environment {name!r}; valid names: {', '.join(domains.NAMES)}")
    return f"{NAMESPACE}/{GYMNASIUM_NAMES[name]}-v{VERSION}"


ENVIRONMENT_IDS: tuple[str, ...] = tuple(environment_id(name) for name in domains.NAMES)


def step_reward(env: Environment, task: int, state: int, next_state: int) -> float:
    """The reward of the step from ``state`` to ``next_state`` in ``task``.

    The exact evaluation counts, as the paper authors' does, the rewards of the states s_1 ..
    s_H that an episode's H transitions reach (``server.learners.evaluation``), so a step pays
    the reward of the state it reaches; tests/rl checks this against the evaluation's own
    function, and fails if the evaluation counts otherwise."""
    return float(env.tasks[task].reward[next_state])


def _palette() -> dict[str, tuple[int, int, int]]:
    """The page's colours (``server.domains.drawing``, those of server/static/js/grid.js;
    tests/rl checks they agree)."""
    hex_colours = {
        **drawing.COLOURS,
        "goal": "#ffffff",
        "outline": "#1f2328",
        "agent": "#0072B2",
    }
    return {key: _rgb(value) for key, value in hex_colours.items()}


def _rgb(hex_colour: str) -> tuple[int, int, int]:
    return (int(hex_colour[1:3], 16), int(hex_colour[3:5], 16), int(hex_colour[5:7], 16))


PALETTE = _palette()


class BAMStudyEnv(gym.Env[Any, np.int64]):
    """One of our environments (``environment``: a registered name or an ``Environment``).

    Actions: ``Discrete(5)`` in our order (STAY, UP, DOWN, LEFT, RIGHT). Observations: the
    state number (``Discrete(num_states)``, the default), or with ``observation="grid"`` a
    ``(height, width, channels)`` array of 0/1 with one channel per kind of cell (walls,
    terrains, colours, machines), the agent's cell, the agent's gravity or carried machine
    (one channel each, set on the agent's cell), and the current task's goal cells: the
    channel names are ``grid_channels``. ``task``: the task of every episode whose ``reset``
    names none (else one drawn at random): the state number does not say which goal to reach,
    so an agent that learns from it alone learns one task at a time.
    """

    metadata = {"render_modes": ["ansi", "rgb_array"], "render_fps": 4}

    def __init__(
        self,
        environment: str | Environment = "doorway",
        observation: str = "state",
        render_mode: str | None = None,
        task: int | None = None,
    ) -> None:
        self.env = domains.make(environment) if isinstance(environment, str) else environment
        self.default_task = None if task is None else self.env.check_task(task)
        if observation not in OBSERVATIONS:
            raise ValueError(f"observation must be one of {OBSERVATIONS}, got {observation!r}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode must be one of {self.metadata['render_modes']} or None, "
                f"got {render_mode!r}"
            )
        self.observation_kind = observation
        self.render_mode = render_mode
        self.action_space = spaces.Discrete(self.env.num_actions)
        self.grid_channels, self._layout_planes = _layout_planes(self.env)
        if observation == "state":
            self.observation_space: spaces.Space[Any] = spaces.Discrete(self.env.num_states)
        else:
            self.observation_space = spaces.Box(
                0,
                1,
                (self.env.height, self.env.width, len(self.grid_channels)),
                dtype=np.uint8,
            )
        self.task = 0
        self.state = 0
        self.steps = 0

    # -- the episode --------------------------------------------------------------------------
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        super().reset(seed=seed)
        options = options or {}
        unknown = sorted(set(options) - {"task"})
        if unknown:
            raise ValueError(f"unknown reset option(s) {unknown}; the one option is 'task'")
        task = options.get("task", self.default_task)
        if task is None:
            self.task = int(self.np_random.integers(len(self.env.tasks)))
        else:
            self.task = self.env.check_task(task)
        self.state = self.env.sample_start(self.task, self.np_random)
        self.steps = 0
        return self._observation(), self._info()

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        if self.steps >= self.env.horizon:
            raise RuntimeError("the episode is over (truncated at the horizon): call reset()")
        action = self.env.check_action(int(action) if isinstance(action, np.ndarray) else action)
        state = self.state
        self.state = self.env.step(state, action, self.np_random)
        self.steps += 1
        reward = step_reward(self.env, self.task, state, self.state)
        truncated = self.steps >= self.env.horizon
        return self._observation(), reward, False, truncated, self._info()

    def _info(self) -> dict[str, Any]:
        return {
            "task": self.task,
            "task_name": self.env.tasks[self.task].name,
            "state": self.state,
            "steps": self.steps,
        }

    # -- observations -------------------------------------------------------------------------
    def _observation(self) -> Any:
        if self.observation_kind == "state":
            return np.int64(self.state)
        return self.grid_observation(self.task, self.state)

    def grid_observation(self, task: int, state: int) -> np.ndarray:
        """The grid observation of ``state`` in ``task`` (see the class docstring)."""
        grid = self._layout_planes.copy()
        row, column = self.env.cell_of(state)
        channel = {name: index for index, name in enumerate(self.grid_channels)}
        grid[row, column, channel["agent"]] = 1
        if self.env.num_features > 1:
            feature = self.env.feature_names[self.env.feature_of(state)]
            grid[row, column, channel[f"agent {feature}"]] = 1
        for goal_row, goal_column in self.env.tasks[self.env.check_task(task)].goal_cells:
            grid[goal_row, goal_column, channel["goal"]] = 1
        return grid

    # -- drawing ------------------------------------------------------------------------------
    def render(self) -> Any:
        if self.render_mode == "ansi":
            return self.text_map()
        if self.render_mode == "rgb_array":
            return self.picture()
        return None

    def text_map(self) -> str:
        """The map as text (the legend of the map files; ``*`` the task's goal, ``@`` the
        agent) and a line saying the task, the agent's gravity or machine and the step."""
        rows = [list(line) for line in _text_cells(self.env)]
        for row, column in self.env.tasks[self.task].goal_cells:
            rows[row][column] = "*"
        row, column = self.env.cell_of(self.state)
        rows[row][column] = "@"
        described = self.env.describe_state(self.state)
        feature = "".join(
            f", {key} {described[key]}" for key in ("gravity", "carrying") if key in described
        )
        status = (
            f"task {self.env.tasks[self.task].name}{feature}, "
            f"step {self.steps} of {self.env.horizon}"
        )
        return "\n".join(["".join(row) for row in rows] + [status]) + "\n"

    def picture(self, show_agent: bool = True) -> np.ndarray:
        """The grid in the page's colours, ``CELL_PIXELS`` per cell: goals as white squares,
        machines and gravity colours as squares of their colour, the agent as a blue disc
        (a study's own names in the colours its environment gives them)."""
        size = CELL_PIXELS
        palette = {**_own_colours(self.env), **PALETTE}
        image = np.zeros((self.env.height * size, self.env.width * size, 3), dtype=np.uint8)

        def fill(row: int, column: int, colour: str, margin: int = 0) -> None:
            image[
                row * size + margin : (row + 1) * size - margin,
                column * size + margin : (column + 1) * size - margin,
            ] = palette[colour]

        layout = self.env.layout
        for row, line in enumerate(layout["terrain"]):
            for column, terrain in enumerate(line):
                fill(row, column, terrain)
        for row, column in layout["walls"]:
            fill(row, column, "wall")
        for row, column in self.env.tasks[self.task].goal_cells:
            fill(row, column, "outline", 2)
            fill(row, column, "goal", 3)
        for item in layout["colours"]:
            fill(item["row"], item["column"], item["colour"], 2)
        for item in layout["machines"]:
            fill(item["row"], item["column"], "outline", 3)
            fill(item["row"], item["column"], item["machine"], 4)
        if not show_agent:
            return image
        row, column = self.env.cell_of(self.state)
        y, x = np.mgrid[0:size, 0:size] + 0.5
        disc = (y - size / 2) ** 2 + (x - size / 2) ** 2 <= (size * 0.35) ** 2
        image[row * size : (row + 1) * size, column * size : (column + 1) * size][disc] = PALETTE[
            "agent"
        ]
        return image


def _own_colours(env: Environment) -> dict[str, tuple[int, int, int]]:
    """The colours of the environment's terrains, machines and colours as the page draws them
    (``layout["drawing"]``: a study's own in its study's colours, else a spare one)."""
    return {
        kind["name"]: _rgb(kind["colour"])
        for kinds in env.layout.get("drawing", {}).values()
        for kind in kinds
    }


def _layout_planes(env: Environment) -> tuple[tuple[str, ...], np.ndarray]:
    """The grid observation's channel names and its fixed planes (walls, terrains, colours,
    machines; the agent's and the goal's channels left at 0)."""
    layout = env.layout
    terrains = sorted({terrain for line in layout["terrain"] for terrain in line})
    colours = sorted({item["colour"] for item in layout["colours"]})
    machines = sorted({item["machine"] for item in layout["machines"]})
    channels: list[str] = []
    if layout["walls"]:
        channels.append("wall")
    if len(terrains) > 1:
        channels += terrains
    channels += colours + machines + ["agent"]
    if env.num_features > 1:
        channels += [f"agent {feature}" for feature in env.feature_names]
    channels.append("goal")
    index = {name: position for position, name in enumerate(channels)}
    planes = np.zeros((env.height, env.width, len(channels)), dtype=np.uint8)
    for row, column in layout["walls"]:
        planes[row, column, index["wall"]] = 1
    if len(terrains) > 1:
        for row, line in enumerate(layout["terrain"]):
            for column, terrain in enumerate(line):
                planes[row, column, index[terrain]] = 1
    for item in layout["colours"]:
        planes[item["row"], item["column"], index[item["colour"]]] = 1
    for item in layout["machines"]:
        planes[item["row"], item["column"], index[item["machine"]]] = 1
    planes.flags.writeable = False
    return tuple(channels), planes


def _text_cells(env: Environment) -> list[str]:
    """The grid in the map files' legend (the domains' letters)."""
    letter_of_terrain = {terrain: letter for letter, terrain in farming.TERRAIN_OF_LETTER.items()}
    # A study's own environment draws its own letters.
    letter_of_terrain.update(
        {name: letter for letter, name in env.legend.get("letters", {}).items()}
    )
    letter_of_terrain["floor"] = navigation.FLOOR
    rows = [[letter_of_terrain[terrain] for terrain in line] for line in env.layout["terrain"]]
    for row, column in env.layout["walls"]:
        rows[row][column] = navigation.WALL
    letter_of_colour = {colour: letter for letter, colour in gravity.COLOURS.items()}
    letter_of_colour.update(letter_of_terrain)
    for item in env.layout["colours"]:
        rows[item["row"]][item["column"]] = letter_of_colour[item["colour"]]
    letter_of_machine = {machine: letter for letter, machine in farming.MACHINE_OF_LETTER.items()}
    letter_of_machine.update(letter_of_terrain)
    for item in env.layout["machines"]:
        rows[item["row"]][item["column"]] = letter_of_machine[item["machine"]]
    return ["".join(row) for row in rows]


def study_environment_id(study: str, name: str) -> str:
    """The Gymnasium id of a study's own environment, ``BAMStudy-<study>/<Name>-v0``
    (Gymnasium ids have one namespace, without '/' or '.', and read ``a:b`` as module ``a``:
    the study's name joins ours with a hyphen)."""
    title = "".join(part.capitalize() for part in name.split("-"))
    return f"{NAMESPACE}-{study}/{title}-v{VERSION}"


def register_study_environments(study: str, names: tuple[str, ...]) -> tuple[str, ...]:
    """Register a study's own environments (registered in ``server.domains`` first) with
    Gymnasium; returns their ids."""
    ids = []
    for name in names:
        env_id = study_environment_id(study, name)
        if env_id not in gym.registry:
            gym.register(
                id=env_id,
                entry_point="server.rl.environments:BAMStudyEnv",
                kwargs={"environment": name},
                max_episode_steps=domains.make(name).horizon,
            )
        _STUDY_IDS[name] = env_id
        ids.append(env_id)
    return tuple(ids)


def register_environments() -> None:
    """Register the eleven ids with Gymnasium (importing ``server.rl`` does it)."""
    for name in domains.NAMES:
        env_id = environment_id(name)
        if env_id in gym.registry:
            continue
        gym.register(
            id=env_id,
            entry_point="server.rl.environments:BAMStudyEnv",
            kwargs={"environment": name},
            max_episode_steps=domains.make(name).horizon,
        )
