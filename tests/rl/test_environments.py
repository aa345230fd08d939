"""The Gymnasium environments: registered under the eleven ids, Gymnasium's own checker passes,
the same dynamics as our transition table (every deterministic row, and a chi-square test of
sampled successors on a stochastic table), returns as our exact evaluation counts them, the
task option, truncation at the horizon, seeding, the grid observation and both renderings."""

from __future__ import annotations

import dataclasses
import re

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from scipy.stats import chisquare

from server import domains
from server.domains.base import ACTIONS, Environment, Task
from server.domains.grid import load_map
from server.learners.evaluation import optimal_returns, task_returns
from server.rl import ENVIRONMENT_IDS, BAMStudyEnv, environment_id
from server.rl.environments import PALETTE
from server.teacher import Teacher
from tests.rl._support import REPOSITORY, run_python

# The ids the issue names.
EXPECTED_IDS = {
    f"BAMStudy/{name}-v0"
    for name in (
        "Wall", "Doorway", "TwoRooms", "ThreeRooms", "Flip", "Choices", "TwoFields",
        "ThreeFields", "NavigationTutorial", "GravityTutorial", "FarmingTutorial",
    )
}  # fmt: skip


def test_the_eleven_ids_are_registered_for_our_eleven_environments() -> None:
    assert set(ENVIRONMENT_IDS) == EXPECTED_IDS
    for name in domains.NAMES:
        env = gym.make(environment_id(name))
        assert env.unwrapped.env is domains.make(name)
        assert env.spec is not None and env.spec.max_episode_steps == domains.make(name).horizon


def test_gymnasium_makes_them_without_an_import_of_ours() -> None:
    """Gymnasium 1.x loads no plugins: the id names our module (``module:id``)."""
    program = (
        "import gymnasium\n"
        "env = gymnasium.make('server.rl:BAMStudy/Doorway-v0')\n"
        "observation, info = env.reset(seed=0, options={'task': 1})\n"
        "print(type(env.unwrapped).__name__, env.unwrapped.env.name, info['task_name'])\n"
    )
    assert run_python(program).split() == ["BAMStudyEnv", "doorway", "B"]


@pytest.mark.parametrize("observation", ["state", "grid"])
@pytest.mark.parametrize("env_id", ENVIRONMENT_IDS)
def test_gymnasiums_checker_passes(env_id: str, observation: str) -> None:
    for render_mode in ("ansi", "rgb_array"):
        env = gym.make(env_id, observation=observation, render_mode=render_mode)
        check_env(env.unwrapped, skip_render_check=False)


@pytest.mark.parametrize("name", domains.NAMES)
def test_every_deterministic_row_of_the_table_is_what_a_step_does(name: str) -> None:
    env = domains.make(name)
    table = env.true_transitions
    gym_env = BAMStudyEnv(name)
    gym_env.reset(seed=0)
    assert gym_env.action_space == gym.spaces.Discrete(len(ACTIONS))
    for state in range(env.num_states):
        for action in range(len(ACTIONS)):
            row = table.probabilities[state, action]
            if row.max() < 1.0:
                continue
            gym_env.state, gym_env.steps = state, 0
            observation, *_ = gym_env.step(action)
            assert observation == table.next_states[state, action, int(np.argmax(row))]


def stochastic(env: Environment) -> Environment:
    """``env`` with the learner's initial model as its dynamics: every move is uncertain."""
    model = env.model.transitions(env.model.initial_parameters())
    return dataclasses.replace(env, true_transitions=model)


@pytest.mark.parametrize("name", domains.ENVIRONMENTS)
def test_sampled_successors_follow_the_table(name: str) -> None:
    """A chi-square test of 4000 sampled steps from each of three uncertain state-action pairs
    (a sampler that took the likeliest successor, or ignored one, fails it)."""
    env = stochastic(domains.make(name))
    table = env.true_transitions
    # Rows with two or more distinct successors (farming's STAY on a field carrying a machine
    # is two entries to the same state: certain).
    uncertain = np.array(
        [
            (state, action)
            for state, action in np.argwhere(table.probabilities.max(axis=2) < 1.0)
            if len(set(table.next_states[state, action][table.probabilities[state, action] > 0]))
            > 1
        ]
    )
    picks = uncertain[np.random.default_rng(1).choice(len(uncertain), 3, replace=False)]
    gym_env = BAMStudyEnv(env)
    gym_env.reset(seed=2)
    samples = 4000
    for state, action in picks:
        expected: dict[int, float] = {}
        for successor, p in zip(
            table.next_states[state, action], table.probabilities[state, action], strict=True
        ):
            if p > 0:
                expected[int(successor)] = expected.get(int(successor), 0.0) + float(p)
        counts = dict.fromkeys(expected, 0)
        for _ in range(samples):
            gym_env.state, gym_env.steps = int(state), 0
            observation, *_ = gym_env.step(int(action))
            assert int(observation) in counts, "a successor the table does not have"
            counts[int(observation)] += 1
        successors = sorted(expected)
        result = chisquare(
            [counts[s] for s in successors], [samples * expected[s] for s in successors]
        )
        assert result.pvalue > 1e-3, (name, int(state), int(action), counts, expected)


def sampled_returns(
    gym_env: gym.Env, task: int, policy: np.ndarray, episodes: int, seed: int
) -> list[tuple[int, float]]:
    """(start state, return) of ``episodes`` episodes of a policy (an action per state)."""
    results = []
    observation, _ = gym_env.reset(seed=seed, options={"task": task})
    for _ in range(episodes):
        start, total, truncated = int(observation), 0.0, False
        while not truncated:
            observation, reward, terminated, truncated, _ = gym_env.step(policy[int(observation)])
            assert not terminated
            total += float(reward)
        results.append((start, total))
        observation, _ = gym_env.reset(options={"task": task})
    return results


@pytest.mark.parametrize("name", domains.NAMES)
def test_the_optimal_policys_sampled_return_is_the_exact_optimal_return(name: str) -> None:
    """Episodes of the teacher's optimal policy: each episode's return equals the evaluation's
    exact return from its start state (the evaluation's function on a copy of the environment
    with one task per start state), and those average to its exact optimal return."""
    env = domains.make(name)
    teacher = Teacher(env, seed=0)
    policies = [np.argmax(teacher.q_values(k), axis=1) for k in range(len(env.tasks))]
    optimal = optimal_returns(env)
    np.testing.assert_allclose(task_returns(env, policies), optimal, atol=1e-9)
    gym_env = gym.make(environment_id(name))
    for task in range(len(env.tasks)):
        episodes = sampled_returns(gym_env, task, policies[task], 60, seed=task)
        starts = sorted({start for start, _ in episodes})
        one_start = dataclasses.replace(
            env,
            tasks=tuple(
                dataclasses.replace(env.tasks[task], start=np.eye(env.num_states)[s])
                for s in starts
            ),
        )
        exact = dict(
            zip(starts, task_returns(one_start, [policies[task]] * len(starts)), strict=True)
        )
        for start, total in episodes:
            assert total == pytest.approx(exact[start], abs=1e-9), (task, start)
        # The exact returns from every start, weighed by the start distribution.
        every_start = np.flatnonzero(env.tasks[task].start)
        all_starts = dataclasses.replace(
            env,
            tasks=tuple(
                dataclasses.replace(env.tasks[task], start=np.eye(env.num_states)[s])
                for s in every_start
            ),
        )
        from_each = task_returns(all_starts, [policies[task]] * len(every_start))
        weighted = float(env.tasks[task].start[every_start] @ from_each)
        assert weighted == pytest.approx(optimal[task], abs=1e-9)
        mean = np.mean([total for _, total in episodes])
        spread = np.std(from_each) / np.sqrt(len(episodes))
        assert abs(mean - optimal[task]) < 5 * spread + 1e-9


def test_a_random_policys_mean_return_is_its_exact_return() -> None:
    """A stochastic policy (uniform over the actions) on a stochastic table: the mean of 1000
    sampled returns is within five standard errors of the evaluation's exact return."""
    env = stochastic(domains.make("wall"))
    uniform = np.full((env.num_states, env.num_actions), 1.0 / env.num_actions)
    exact = task_returns(env, [uniform] * len(env.tasks))
    gym_env = BAMStudyEnv(env)
    rng = np.random.default_rng(3)
    for task in range(len(env.tasks)):
        gym_env.reset(seed=10 + task, options={"task": task})
        totals = []
        for _ in range(1000):
            gym_env.reset(options={"task": task})
            total, truncated = 0.0, False
            while not truncated:
                _, reward, _, truncated, _ = gym_env.step(int(rng.integers(env.num_actions)))
                total += float(reward)
            totals.append(total)
        error = np.std(totals) / np.sqrt(len(totals))
        assert abs(np.mean(totals) - exact[task]) < 5 * error


def test_the_task_option_and_truncation_at_the_horizon() -> None:
    env = domains.make("doorway")
    gym_env = gym.make(environment_id("doorway"), observation="grid")
    for task in range(len(env.tasks)):
        observation, info = gym_env.reset(seed=task, options={"task": task})
        assert info["task"] == task and info["task_name"] == env.tasks[task].name
        goal = {tuple(cell) for cell in np.argwhere(observation[:, :, -1] == 1)}
        assert goal == set(env.tasks[task].goal_cells)
        for step in range(1, env.horizon + 1):
            _, _, terminated, truncated, _ = gym_env.step(0)
            assert not terminated and truncated == (step == env.horizon)
    with pytest.raises(RuntimeError, match="reset"):
        gym_env.unwrapped.step(0)
    drawn = {gym_env.reset(seed=seed)[1]["task"] for seed in range(40)}
    assert drawn == set(range(len(env.tasks)))
    fixed = gym.make(environment_id("doorway"), task=2)
    assert {fixed.reset(seed=seed)[1]["task"] for seed in range(10)} == {2}
    assert fixed.reset(options={"task": 1})[1]["task"] == 1
    with pytest.raises(ValueError, match="task 7 out of range"):
        BAMStudyEnv("doorway", task=7)
    with pytest.raises(ValueError, match="task 4 out of range"):
        gym_env.reset(options={"task": 4})
    with pytest.raises(ValueError, match="unknown reset option"):
        gym_env.reset(options={"tsak": 1})
    with pytest.raises(ValueError, match="observation must be one of"):
        BAMStudyEnv("doorway", observation="pixels")


def test_seeding_reproduces_episodes() -> None:
    def episode(seed: int) -> list[int]:
        env = gym.make(environment_id("three-fields"))
        env.action_space.seed(seed)
        observation, _ = env.reset(seed=seed)
        visited = [int(observation)]
        for _ in range(30):
            visited.append(int(env.step(env.action_space.sample())[0]))
        return visited

    assert episode(5) == episode(5)
    assert episode(5) != episode(6)
    starts = {int(gym.make(environment_id("flip")).reset(seed=s)[0]) for s in range(10)}
    assert len(starts) > 1


@pytest.mark.parametrize("name", domains.NAMES)
def test_the_grid_observation_shows_the_agent_its_feature_and_the_layout(name: str) -> None:
    env = domains.make(name)
    gym_env = BAMStudyEnv(name, observation="grid")
    channel = {c: i for i, c in enumerate(gym_env.grid_channels)}
    seen = set()
    for state in range(env.num_states):
        grid = gym_env.grid_observation(0, state)
        assert gym_env.observation_space.contains(grid)
        (cell,) = np.argwhere(grid[:, :, channel["agent"]] == 1)
        assert tuple(cell) == env.cell_of(state)
        if env.num_features > 1:
            features = grid[:, :, [channel[f"agent {f}"] for f in env.feature_names]]
            assert features.sum() == 1
            assert features[cell[0], cell[1]].argmax() == env.feature_of(state)
        seen.add(grid.tobytes())
    assert len(seen) == env.num_states  # one observation per state
    walls = (
        {tuple(cell) for cell in np.argwhere(grid[:, :, channel["wall"]] == 1)}
        if ("wall" in channel)
        else set()
    )
    assert walls == {tuple(cell) for cell in env.layout["walls"]}
    for item in env.layout["machines"]:
        assert grid[item["row"], item["column"], channel[item["machine"]]] == 1
    for item in env.layout["colours"]:
        assert grid[item["row"], item["column"], channel[item["colour"]]] == 1


@pytest.mark.parametrize("name", [n for n in domains.NAMES if n != "gravity-tutorial"])
def test_the_text_rendering_is_the_map(name: str) -> None:
    """The ansi rendering draws the map file's grid (goal letters as the floor they stand on,
    the task's goal as *, the agent as @) and says the task."""
    env = domains.make(name)
    grid_map = load_map(name)
    gym_env = gym.make(environment_id(name), render_mode="ansi")
    _, info = gym_env.reset(seed=0, options={"task": 0})
    *rows, status = gym_env.render().rstrip("\n").split("\n")
    goal = set(env.tasks[0].goal_cells)
    agent = env.cell_of(info["state"])
    for r, (drawn, mapped) in enumerate(zip(rows, grid_map.grid, strict=True)):
        for c, (char, mapped_char) in enumerate(zip(drawn, mapped, strict=True)):
            if (r, c) == agent:
                assert char == "@"
            elif (r, c) in goal:
                assert char == "*"
            elif mapped_char in grid_map.goal_letters:
                assert char == "."
            else:
                assert char == mapped_char, (r, c)
    assert status.startswith(f"task {env.tasks[0].name}")


def test_the_picture_uses_the_pages_colours() -> None:
    script = (REPOSITORY / "server/static/js/grid.js").read_text()
    for name in ("floor", "dirt", "soil", "grass", "crops", "orange", "green", "purple"):
        match = re.search(rf'{name}: \{{ fill: "#([0-9a-fA-F]{{6}})"', script)
        assert match is not None, name
        assert PALETTE[name] == tuple(int(match.group(1)[i : i + 2], 16) for i in (0, 2, 4))
    env = domains.make("two-fields")
    gym_env = gym.make(environment_id("two-fields"), render_mode="rgb_array")
    _, info = gym_env.reset(seed=0, options={"task": 0})
    picture = gym_env.render()
    assert picture.shape == (env.height * 16, env.width * 16, 3) and picture.dtype == np.uint8
    row, column = env.cell_of(info["state"])
    assert tuple(picture[row * 16 + 8, column * 16 + 8]) == PALETTE["agent"]
    soil_row, soil_column = env.tasks[0].goal_cells[0]
    assert tuple(picture[soil_row * 16 + 8, soil_column * 16 + 8]) == PALETTE["goal"]
    assert tuple(picture[soil_row * 16 + 1, soil_column * 16 + 1]) == PALETTE["soil"]


def test_the_picture_draws_a_study_s_own_kinds_in_the_page_s_colours() -> None:
    """The study's colour where it gives one, the page's spare colour where it does not (the
    picture has a colour for every kind, as the page does)."""
    from server.domains.drawing import SPARE_COLOURS
    from server.domains.spec import EnvironmentSpec

    text = """task: Vines = rows 1-2, columns 1-2
task: Moss = rows 1-2, columns 4-5
start: rows 3-4
    0123456
  0 .......
  1 .vv.mm.
  2 .vv.mm.
  3 .......
  4 T.Q....
"""
    env = EnvironmentSpec(
        name="own-kinds",
        domain="farming",
        map=text,
        terrains={"v": "vines", "m": "moss"},
        machines={"T": "trellis", "Q": "quad"},
        works_on={"trellis": "vines", "quad": "moss"},
        colours={"vines": "#6b8e23"},
    ).build()
    picture = BAMStudyEnv(env, render_mode="rgb_array").picture(show_agent=False)

    def rgb(hex_colour: str) -> tuple[int, ...]:
        return tuple(int(hex_colour[i : i + 2], 16) for i in (1, 3, 5))

    drawn = {k["name"]: k["colour"] for kinds in env.layout["drawing"].values() for k in kinds}
    assert drawn["vines"] == "#6b8e23" and drawn["moss"] in SPARE_COLOURS
    # Outside the goal's outline (task 0 is the vines): the terrain's colour.
    assert tuple(picture[1 * 16 + 1, 4 * 16 + 1]) == rgb(drawn["moss"])
    assert tuple(picture[4 * 16 + 8, 0 * 16 + 8]) == rgb(drawn["trellis"])
    assert tuple(picture[4 * 16 + 8, 2 * 16 + 8]) == rgb(drawn["quad"])


def test_the_reward_is_counted_as_the_evaluation_counts_it() -> None:
    """A start on the goal and a first move off it, then staying: the two ways of counting
    (the states before each action, or after) differ by one here. The sampled return is the
    evaluation's exact return of that policy from that start."""
    env = domains.make("wall")
    goal = env.tasks[0].goal_cells[0]
    start = env.state_of(*goal)
    table = env.true_transitions
    away = next(
        a
        for a in range(len(ACTIONS))
        if table.probabilities[start, a].max() == 1.0
        and not env.is_goal(
            0, int(table.next_states[start, a, table.probabilities[start, a].argmax()])
        )
    )
    policy = np.zeros(env.num_states, dtype=np.int64)
    policy[start] = away
    one = dataclasses.replace(
        env, tasks=(Task("A", env.tasks[0].reward, np.eye(env.num_states)[start], (goal,)),)
    )
    exact = task_returns(one, [policy])[0]
    gym_env = BAMStudyEnv(one)
    observation, _ = gym_env.reset(seed=0, options={"task": 0})
    assert observation == start
    total = 0.0
    for _ in range(env.horizon):
        observation, reward, *_ = gym_env.step(policy[int(observation)])
        total += reward
    assert total == exact
