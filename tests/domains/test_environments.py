"""Properties every registered environment has: sizes, valid and deterministic true dynamics,
tasks and start distributions, goals reachable within the horizon, and ``step``."""

from __future__ import annotations

from collections import deque
from importlib import resources

import numpy as np
import pytest

from server import domains
from server.domains.base import NUM_ACTIONS, Environment

# name: (height, width, features, states, horizon, task names)
EXPECTED: dict[str, tuple[int, int, int, int, int, tuple[str, ...]]] = {
    "wall": (9, 9, 1, 81, 36, ("A", "B")),
    "doorway": (11, 11, 1, 121, 44, ("A", "B", "C", "D")),
    "two-rooms": (8, 15, 1, 120, 46, ("A", "B", "C")),
    "three-rooms": (13, 13, 1, 169, 52, ("A", "B")),
    "flip": (10, 10, 4, 400, 80, ("A", "B")),
    "choices": (4, 15, 4, 240, 76, ("A", "B")),
    "two-fields": (8, 12, 4, 384, 80, ("Soil field", "Crops field")),
    "three-fields": (8, 12, 4, 384, 80, ("Soil field",)),
    "navigation-tutorial": (11, 11, 1, 121, 44, ("Top", "Bottom")),
    "farming-tutorial": (10, 12, 4, 480, 88, ("Soil", "Grass", "Crops")),
    "gravity-tutorial": (10, 10, 4, 400, 80, ("A", "B")),
}
FEATURES = {
    "navigation": ("none",),
    "gravity": ("north", "south", "east", "west"),
    "farming": ("none", "plow", "sprinkler", "harvester"),
}
# Gravity starts are every cell with every gravity, as the reference says; an agent whose
# gravity pins it to the edge column away from a goal (east gravity forbids LEFT, west forbids
# RIGHT, and no colour lies in that column) can never reach that goal. These are exactly the
# start states from which a goal is unreachable; every other start reaches its goal in time.
EAST, WEST = 2, 3
# (row, column, gravity) states of the reference's "any cell, any gravity" from which no policy
# can reach the task's goal; the start distributions leave exactly these out.
UNREACHABLE: dict[tuple[str, str], set[tuple[int, int, int]]] = {
    ("flip", "A"): {(r, 9, EAST) for r in range(10)},
    ("flip", "B"): {(r, 0, WEST) for r in range(10)},
    ("choices", "A"): {(r, 14, EAST) for r in range(4)},
    ("choices", "B"): {(r, 0, WEST) for r in range(4)},
    ("gravity-tutorial", "A"): {(r, 9, EAST) for r in range(10)},
    ("gravity-tutorial", "B"): {(r, 0, WEST) for r in range(10)},
}


def true_successors(env: Environment) -> np.ndarray:
    """(S, A) array of the single successor of each (state, action) under the true dynamics."""
    transitions = env.transition_probabilities()
    assert np.all((transitions == 0.0) | (transitions == 1.0))
    assert np.all(transitions.sum(axis=2) == 1.0)
    return transitions.argmax(axis=2)


def steps_to_goal(env: Environment, reward: np.ndarray) -> np.ndarray:
    """Fewest true-dynamics steps from each state to a goal state (-1: never), by breadth-first
    search backwards from the goal states."""
    successors = true_successors(env)
    predecessors: list[list[int]] = [[] for _ in range(env.num_states)]
    for state in range(env.num_states):
        for successor in set(successors[state].tolist()):
            predecessors[successor].append(state)
    distance = np.full(env.num_states, -1)
    queue = deque(int(s) for s in np.flatnonzero(reward > 0))
    distance[list(queue)] = 0
    while queue:
        state = queue.popleft()
        for predecessor in predecessors[state]:
            if distance[predecessor] < 0:
                distance[predecessor] = distance[state] + 1
                queue.append(predecessor)
    return distance


def test_registry_names() -> None:
    assert domains.NAMES == (
        "wall",
        "doorway",
        "two-rooms",
        "three-rooms",
        "flip",
        "choices",
        "two-fields",
        "three-fields",
        "navigation-tutorial",
        "farming-tutorial",
        "gravity-tutorial",
    )
    assert domains.ENVIRONMENTS == domains.NAMES[:8]
    assert domains.DOMAINS == {
        "navigation": ("wall", "doorway", "two-rooms", "three-rooms"),
        "gravity": ("flip", "choices"),
        "farming": ("two-fields", "three-fields"),
    }
    assert domains.TUTORIALS == {
        "navigation": "navigation-tutorial",
        "gravity": "gravity-tutorial",
        "farming": "farming-tutorial",
    }


def test_every_map_file_is_registered() -> None:
    maps = resources.files("server.domains").joinpath("maps")
    names = {
        path.name.removesuffix(".txt") for path in maps.iterdir() if path.name.endswith(".txt")
    }
    # The gravity tutorial is drawn on the flip map.
    assert names == set(domains.NAMES) - {"gravity-tutorial"}


@pytest.mark.parametrize("name", domains.NAMES)
def test_make_is_cached_and_read_only(name: str) -> None:
    env = domains.make(name)
    assert domains.make(name) is env
    assert env.name == name and domains.domain_of(name) == env.domain
    with pytest.raises(ValueError, match="read-only"):
        env.true_transitions.probabilities[0, 0, 0] = 0.5
    with pytest.raises(ValueError, match="read-only"):
        env.tasks[0].reward[0] = 1.0
    with pytest.raises(ValueError, match="read-only"):
        env.model.coef[0, 0, 0] = 1.0


@pytest.mark.parametrize("name", domains.NAMES)
def test_sizes_horizon_tasks(name: str) -> None:
    env = domains.make(name)
    height, width, features, states, horizon, task_names = EXPECTED[name]
    assert (env.height, env.width, env.num_features) == (height, width, features)
    assert env.num_states == states and env.num_actions == NUM_ACTIONS == 5
    assert env.horizon == horizon
    assert env.horizon == (2 if env.domain == "navigation" else 4) * (height + width)
    assert env.task_names == task_names
    assert env.feature_names == FEATURES[env.domain]
    assert np.array_equal(env.state_cells, np.arange(states) // features)


@pytest.mark.parametrize("name", domains.NAMES)
def test_true_transitions_valid_and_deterministic(name: str) -> None:
    env = domains.make(name)
    transitions = env.transition_probabilities()
    assert transitions.shape == (env.num_states, NUM_ACTIONS, env.num_states)
    assert np.all(transitions >= 0.0)
    np.testing.assert_allclose(transitions.sum(axis=2), 1.0, rtol=0, atol=1e-12)
    # Deterministic everywhere: one successor with probability 1 per row.
    successors = true_successors(env)
    # STAY stays in its cell (in gravity, acting from a coloured cell sets its gravity; the
    # state stays elsewhere); every move goes to the same cell or a neighbouring one.
    assert np.array_equal(env.state_cells[successors[:, 0]], env.state_cells)
    if env.domain != "gravity":
        assert np.array_equal(successors[:, 0], np.arange(env.num_states))
    cells = env.state_cells[successors]
    rows, columns = np.divmod(cells, env.width)
    here_rows, here_columns = np.divmod(env.state_cells, env.width)
    assert np.all(np.abs(rows - here_rows[:, None]) + np.abs(columns - here_columns[:, None]) <= 1)
    # The sparse true transitions share the model's successor lists (padded with zeros).
    assert env.true_transitions.next_states.shape == env.model.next_states.shape
    assert np.array_equal(env.true_transitions.next_states, env.model.next_states)
    assert set(np.unique(env.true_transitions.probabilities)) <= {0.0, 1.0}


@pytest.mark.parametrize("name", domains.NAMES)
def test_tasks_rewards_and_starts(name: str) -> None:
    env = domains.make(name)
    description = env.describe()
    walls = {tuple(cell) for cell in description["walls"]}
    machines = {(m["row"], m["column"]) for m in description["machines"]}
    for task in env.tasks:
        assert task.reward.shape == task.start.shape == (env.num_states,)
        goal_states = {
            env.state_of(r, c, f) for r, c in task.goal_cells for f in range(env.num_features)
        }
        assert set(np.flatnonzero(task.reward).tolist()) == goal_states
        assert set(np.unique(task.reward)) == {0.0, 1.0}
        for start in (task.start, task.study_start_distribution):
            assert np.all(start >= 0.0) and start.sum() == pytest.approx(1.0, abs=1e-12)
            support = np.flatnonzero(start)
            np.testing.assert_allclose(start[support], 1.0 / len(support), rtol=1e-12)
            start_cells = {env.cell_of(int(s)) for s in support}
            assert not start_cells & walls and not start_cells & machines
            if env.domain == "farming":
                # Carrying nothing, on dirt.
                assert all(env.feature_of(int(s)) == 0 for s in support)
                terrain = description["terrain"]
                assert all(terrain[r][c] == "dirt" for r, c in start_cells)


@pytest.mark.parametrize(
    ("name", "rows", "columns", "features"),
    [
        ("wall", range(9), range(9), 1),
        ("doorway", range(8, 11), range(11), 1),
        ("two-rooms", range(8), range(15), 1),
        ("three-rooms", range(13), range(13), 1),
        ("navigation-tutorial", range(11), range(11), 1),
        ("flip", range(10), range(10), 4),
        ("choices", range(4), range(15), 4),
        ("gravity-tutorial", range(10), range(10), 4),
        ("two-fields", range(8), range(12), 1),
        ("three-fields", range(8), range(12), 1),
        ("farming-tutorial", range(10), range(12), 1),
    ],
)
def test_start_regions(name: str, rows: range, columns: range, features: int) -> None:
    """The study's starts cover exactly the allowed cells of the reference's start region
    (with every gravity in gravity, carrying nothing in farming), less the states from which
    the goal cannot be reached; the simulations' starts are the same, except that gravity's
    keep those states (as the authors' do) and Two Rooms' are its study regions."""
    env = domains.make(name)
    description = env.describe()
    blocked = {tuple(cell) for cell in description["walls"]}
    blocked |= {(m["row"], m["column"]) for m in description["machines"]}
    terrain = description["terrain"]
    expected = {
        env.state_of(r, c, f)
        for r in rows
        for c in columns
        for f in range(features)
        if (r, c) not in blocked and terrain[r][c] in ("floor", "dirt")
    }
    for task in env.tasks:
        excluded = {env.state_of(*rcf) for rcf in UNREACHABLE.get((name, task.name), set())}
        assert excluded <= expected
        study = set(np.flatnonzero(task.study_start_distribution).tolist())
        simulation = set(np.flatnonzero(task.start).tolist())
        if name == "two-rooms":  # the study's regions (test_two_rooms_study_starts)
            assert simulation == study < expected
            continue
        assert study == expected - excluded
        if env.domain == "gravity":
            assert simulation == expected
        else:
            assert task.study_start is None
            assert task.study_start_distribution is task.start


def test_two_rooms_study_starts() -> None:
    env = domains.make("two-rooms")
    walls = {tuple(cell) for cell in env.describe()["walls"]}

    def free_in(columns: range) -> set[int]:
        return {env.state_of(r, c) for r in range(8) for c in columns if (r, c) not in walls}

    expected = {"A": free_in(range(3)), "B": free_in(range(12, 15)), "C": free_in(range(3))}
    for task in env.tasks:
        assert task.study_start is not None
        assert set(np.flatnonzero(task.study_start).tolist()) == expected[task.name]
        assert len(expected[task.name]) == 24  # columns 0-2 and 12-14 have no walls
    rng_a, rng_b = np.random.default_rng(3), np.random.default_rng(3)
    starts = [env.sample_start(1, rng_a, study=True) for _ in range(50)]
    assert starts == [env.sample_start(1, rng_b, study=True) for _ in range(50)]
    assert all(env.cell_of(s)[1] >= 12 for s in starts)


@pytest.mark.parametrize("name", domains.NAMES)
def test_goals_reachable_within_horizon(name: str) -> None:
    env = domains.make(name)
    for task in env.tasks:
        distance = steps_to_goal(env, task.reward)
        # Gravity simulations start anywhere, as the authors' do (test_start_regions).
        starts = [task.study_start_distribution]
        if env.domain != "gravity":
            starts.append(task.start)
        for start in starts:
            support = np.flatnonzero(start)
            unreachable = {
                (*env.cell_of(int(s)), env.feature_of(int(s))) for s in support if distance[s] < 0
            }
            assert unreachable == set()
            reachable = distance[support][distance[support] >= 0]
            assert reachable.max() <= env.horizon - 1


@pytest.mark.parametrize("name", domains.NAMES)
def test_step_agrees_with_transition_probabilities(name: str) -> None:
    env = domains.make(name)
    successors = true_successors(env)
    rng = np.random.default_rng(0)
    stepped = np.array(
        [[env.step(s, a, rng) for a in range(NUM_ACTIONS)] for s in range(env.num_states)]
    )
    assert np.array_equal(stepped, successors)


@pytest.mark.parametrize("name", domains.NAMES)
def test_episodes_reproducible_from_a_seed(name: str) -> None:
    env = domains.make(name)

    def episode(seed: int) -> list[int]:
        rng = np.random.default_rng(seed)
        task = int(rng.integers(len(env.tasks)))
        states = [env.sample_start(task, rng)]
        for _ in range(env.horizon):
            states.append(env.step(states[-1], int(rng.integers(NUM_ACTIONS)), rng))
        return states

    assert episode(7) == episode(7)
    assert any(episode(7) != episode(seed) for seed in range(8, 12))
