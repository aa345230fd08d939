"""Environments a study defines (server.domains.spec): one test per problem the checks report,
with its line and column; every problem of a map reported at once; registration by name; and
properties over many random valid maps of each domain."""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from server import domains
from server.domains.base import NUM_ACTIONS, Environment
from server.domains.grid import MapProblems, Problem
from server.domains.spec import EnvironmentSpec
from server.learners import make as make_learner
from server.learners.base import dumps, loads
from server.learners.evaluation import optimal_returns
from server.learners.planning import soft_value_iteration
from server.teacher import Teacher

# Line 1 is the task, line 5 the grid's row 0; a cell (r, c) is at line 5 + r, column 5 + c.
NAVIGATION = """task: A
task: B
start: rows 3-4
    012345
  0 A..#.B
  1 ...#..
  2 ......
  3 ......
  4 ......
"""


def spec(text: str = NAVIGATION, domain: str = "navigation", **keys: object) -> EnvironmentSpec:
    return EnvironmentSpec(name="custom", domain=domain, map=text, **keys)  # type: ignore[arg-type]


def only(problems: list[Problem]) -> Problem:
    assert len(problems) == 1, problems
    return problems[0]


def test_a_valid_map_has_no_problem_and_builds_as_its_family_does() -> None:
    env = spec().build()
    assert spec().problems() == []
    assert (env.domain, env.height, env.width, env.horizon) == ("navigation", 5, 6, 22)
    assert env.task_names == ("A", "B")
    assert env.layout["walls"] == [[0, 3], [1, 3]]
    # Starts: the 12 free cells of rows 3-4, uniformly.
    assert np.count_nonzero(env.tasks[0].start) == 12


def test_the_built_in_maps_pass_the_checks_and_build_the_same_environments() -> None:
    from importlib import resources

    # The paper's gravity maps start the simulations in every gravity, the few trapped ones
    # included (1.7% of choices' starts): a copy accepts them as a study would, by saying so.
    accepted = {"choices": 0.02}
    for name in ("doorway", "two-rooms", "choices", "two-fields"):
        text = resources.files("server.domains").joinpath(f"maps/{name}.txt").read_text()
        domain = domains.domain_of(name)
        copy = EnvironmentSpec(f"copy-{name}", domain, text)
        assert bool(copy.problems()) == (name in accepted)
        env = replace(copy, max_trapped_start_share=accepted.get(name, 0.0)).build()
        built_in = domains.make(name)
        assert env.layout == built_in.layout
        assert np.array_equal(
            env.true_transitions.next_states, built_in.true_transitions.next_states
        )
        assert np.allclose(optimal_returns(env), optimal_returns(built_in))


# -- one test per problem ------------------------------------------------------------------


def test_an_unknown_letter_is_reported_at_its_line_and_column() -> None:
    problem = only(spec(NAVIGATION.replace("  2 ......", "  2 ..x...")).problems())
    assert (problem.line, problem.column) == (7, 7)
    assert "unknown character 'x'" in problem.message and "row 2, column 2" in problem.message


def test_a_task_whose_letter_is_not_drawn_has_no_goal_cell() -> None:
    problem, letter = spec(NAVIGATION.replace("task: B", "task: C")).problems()
    assert (problem.line, problem.column) == (2, 7)
    assert "task 'C' has no goal cell" in problem.message
    # B is no task's letter any more.
    assert (letter.line, letter.column) == (5, 10) and "unknown character 'B'" in letter.message


def test_a_task_with_no_reachable_goal_cell_is_reported_at_its_task_line() -> None:
    walled = NAVIGATION.replace("  1 ...#..", "  1 ...###").replace("  0 A..#.B", "  0 A..#.B")
    problem = only(spec(walled).problems())
    assert (problem.line, problem.column) == (2, 7)
    assert "task 'B': no goal cell can be reached" in problem.message


def test_a_goal_beyond_the_horizon_is_not_reachable() -> None:
    # Rows 3-4 are at least 3 moves from either goal.
    problems = spec(horizon=2).problems()
    assert [(p.line, p.column) for p in problems] == [(1, 7), (2, 7)]
    assert all(
        "can be reached from the start region within the horizon of 2" in p.message
        for p in problems
    )


def test_an_empty_start_region_is_reported_at_its_start_line() -> None:
    walled_rows = NAVIGATION.replace("  4 ......", "  4 ######").replace("rows 3-4", "rows 4")
    problems = spec(walled_rows).problems()
    assert [(p.line, p.column) for p in problems] == [(3, 8), (3, 8)]
    assert all("the start region has no start cell" in p.message for p in problems)


def test_start_cells_walled_in_are_named_as_trapped() -> None:
    # Row 4's two right cells are walled in by row 3's wall and the grid's edge.
    text = NAVIGATION.replace("  3 ......", "  3 ....##").replace("  4 ......", "  4 ...#..")
    problems = spec(text).problems()
    assert len(problems) == 2  # tasks A and B
    assert {(p.line, p.column) for p in problems} == {(9, 9)}  # cell (4, 4)
    # Walled in, they can never reach it: trapped, named, no share of them to accept.
    assert all("2 of its 9 start states" in p.message for p in problems)
    assert all("(row 4, columns 4-5)" in p.message for p in problems)
    assert not any("max_trapped_start_share" in p.message for p in problems)


def test_a_machine_that_can_never_be_reached_is_reported_at_its_cell() -> None:
    text = """task: Soil = rows 0, columns 0-1
start: columns 0-2
    0123456
  0 ss.cc.H
  1 ...cc..
  2 P..cc..
"""
    # The harvester stands behind crops, which only the harvester enters.
    problem = only(spec(text, "farming").problems())
    assert (problem.line, problem.column) == (4, 11)
    assert "the harvester at (row 0, column 6) can never be reached" in problem.message


def test_a_map_larger_than_the_study_allows_is_reported_with_its_size() -> None:
    problem = only(spec().problems(max_states=20))
    assert (problem.line, problem.column) == (5, 5)
    assert "30 states" in problem.message and "more than the 20 the study allows" in problem.message


def test_a_goal_on_a_wall_a_colour_or_dirt_is_reported() -> None:
    wall_goal = NAVIGATION.replace("task: B", "task: B\ntask: W = rows 0-1, columns 3")
    assert "the goal of task 'W' is a wall" in only(spec(wall_goal).problems()).message
    gravity_map = "task: A = rows 0, columns 0-1\nstart: anywhere\ngravity of orange: south\n"
    gravity_map += "    012\n  0 .o.\n  1 ...\n"
    assert "is coloured" in only(spec(gravity_map, "gravity").problems()).message
    dirt = "task: F = rows 0, columns 0-2\nstart: anywhere\n    0123\n  0 ss..\n  1 P...\n"
    assert "must cover one field terrain" in only(spec(dirt, "farming").problems()).message


def test_a_colour_without_a_gravity_and_a_gravity_without_a_colour_are_reported() -> None:
    text = "task: A\nstart: anywhere\ngravity of green: up\n    0123\n  0 .o.A\n  1 ....\n"
    problems = spec(text, "gravity").problems()
    assert [(p.line, p.column) for p in problems] == [(3, 19), (5, 6)]
    assert "no green cell" in problems[0].message
    assert "no gravity for orange" in problems[1].message


def test_a_bad_direction_is_reported_at_its_line() -> None:
    text = "task: A\nstart: anywhere\ngravity of orange: up\n    0123\n  0 .o.A\n  1 ....\n"
    problem = only(spec(text, "gravity").problems())
    assert (problem.line, problem.column) == (3, 20)
    assert "'up' is not one of north, south, east, west" in problem.message


def test_the_text_s_own_problems_keep_their_lines() -> None:
    text = NAVIGATION.replace("  1 ...#..", "  1 ...#.").replace("start:", "begin:")
    problems = spec(text).problems()
    assert [(p.line, p.column) for p in problems] == [(3, 1), (6, 10)]
    assert "unknown header key 'begin'" in problems[0].message
    assert "row 1 is 5 cells wide" in problems[1].message


def test_problems_of_the_definition_s_keys() -> None:
    bad = spec(domain="navigation", terrains={"v": "vines"}, horizon=0)
    messages = [str(problem) for problem in bad.problems()]
    assert any("horizon 0 is not a whole number" in m for m in messages)
    assert any("terrains: a navigation environment has no terrains" in m for m in messages)
    assert "domain 'kitchen'" in str(only(spec(domain="kitchen").problems()))
    farm = "task: F = rows 0, columns 0-1\nstart: anywhere\n    0123\n  0 vv.T\n  1 P...\n"
    messages = [
        str(p)
        for p in spec(
            farm, "farming", terrains={"v": "vines", "S": "stone"}, machines={"T": "trellis"}
        ).problems()
    ]
    assert "works_on: say which terrain the trellis works on" in messages
    assert any("terrains.S: a map letter here is one lower-case letter" in m for m in messages)


def test_every_problem_is_reported_at_once() -> None:
    text = (
        NAVIGATION.replace("task: B", "task: C")
        .replace("  2 ......", "  2 ..x...")
        .replace("  3 ......", "  3 ....##")
        .replace("  4 ......", "  4 ...#.?")
    )
    with pytest.raises(MapProblems) as raised:
        spec(text).build()
    problems = raised.value.problems
    # Task C's goal, the letter B (no task's now), x, the cut-off cells (4, 4) and (4, 5)
    # (the first of them named) and '?'.
    assert [(p.line, p.column) for p in problems] == [(2, 7), (5, 10), (7, 7), (9, 9), (9, 10)]
    assert "task 'A': 2 of its 9 start states" in problems[3].message
    assert "has 5 problems" in str(raised.value)
    assert "line 9, column 10: unknown character '?'" in str(raised.value)


# -- registration -------------------------------------------------------------------------


@pytest.fixture
def registered() -> Iterator[Environment]:
    env = domains.register(spec())
    yield env
    domains.unregister("custom")


def test_a_registered_environment_is_found_by_name(registered: Environment) -> None:
    assert domains.make("custom") is registered
    assert domains.domain_of("custom") == "navigation"
    assert "custom" in domains.names() and domains.registered() == (spec(),)
    assert domains.register(spec()) is registered  # the same definition again
    with pytest.raises(ValueError, match="already defined differently"):
        domains.register(spec(horizon=30))


def test_an_unregistered_or_built_in_name_is_refused() -> None:
    with pytest.raises(ValueError, match="unknown environment 'custom'"):
        domains.make("custom")
    with pytest.raises(ValueError, match="built in"):
        domains.register(EnvironmentSpec(name="doorway", domain="navigation", map=NAVIGATION))


# -- properties over random maps -----------------------------------------------------------


@st.composite
def navigation_maps(draw: st.DrawFn) -> EnvironmentSpec:
    height, width = draw(st.integers(2, 5)), draw(st.integers(2, 6))
    walls = draw(st.lists(st.booleans(), min_size=height * width, max_size=height * width))
    goal = (draw(st.integers(0, height - 1)), draw(st.integers(0, width - 1)))
    rows = [["#" if walls[r * width + c] else "." for c in range(width)] for r in range(height)]
    rows[goal[0]][goal[1]] = "A"
    return EnvironmentSpec("random", "navigation", _text(rows, "task: A\nstart: anywhere\n"))


@st.composite
def gravity_maps(draw: st.DrawFn) -> EnvironmentSpec:
    height, width = draw(st.integers(2, 4)), draw(st.integers(2, 5))
    cells = draw(
        st.lists(st.sampled_from(".....og"), min_size=height * width, max_size=height * width)
    )
    rows = [list(cells[r * width : (r + 1) * width]) for r in range(height)]
    # At least one colour (the model space has a parameter), then the goal elsewhere.
    coloured = draw(st.integers(0, height * width - 1))
    rows[coloured // width][coloured % width] = "o"
    goal = divmod((coloured + draw(st.integers(1, height * width - 1))) % (height * width), width)
    rows[goal[0]][goal[1]] = "A"
    header = "task: A\nstart: anywhere\n"
    for letter, colour in (("o", "orange"), ("g", "green")):
        if any(letter in row for row in rows):
            direction = draw(st.sampled_from(["north", "south", "east", "west"]))
            header += f"gravity of {colour}: {direction}\n"
    return EnvironmentSpec("random", "gravity", _text(rows, header))


@st.composite
def farming_maps(draw: st.DrawFn) -> EnvironmentSpec:
    height, width = draw(st.integers(3, 4)), draw(st.integers(3, 6))
    cells = draw(
        st.lists(st.sampled_from("......sicv"), min_size=height * width, max_size=height * width)
    )
    rows = [list(cells[r * width : (r + 1) * width]) for r in range(height)]
    for letter in "PWHT":
        rows[draw(st.integers(0, height - 1))][draw(st.integers(0, width - 1))] = letter
    goal = (draw(st.integers(0, height - 1)), draw(st.integers(0, width - 1)))
    rows[goal[0]][goal[1]] = draw(st.sampled_from("sicv"))
    if not any("." in row for row in rows):
        # "anywhere" starts on free dirt: a map with none has no start cell, a fault of its
        # letters, not of reachability. The first cell that is not a machine or the goal.
        r, c = next(
            (r, c)
            for r in range(height)
            for c in range(width)
            if rows[r][c] not in "PWHT" and (r, c) != goal
        )
        rows[r][c] = "."
    header = f"task: F = rows {goal[0]}, columns {goal[1]}\nstart: anywhere\n"
    return EnvironmentSpec(
        "random",
        "farming",
        _text(rows, header),
        terrains={"v": "vines"},
        machines={"T": "trellis"},
        works_on={"trellis": "vines"},
    )


def _text(rows: list[list[str]], header: str) -> str:
    width = len(rows[0])
    lines = ["    " + "".join(str(c % 10) for c in range(width))]
    lines += [f"{r:>3} {''.join(row)}" for r, row in enumerate(rows)]
    return header + "\n".join(lines) + "\n"


def _distances(env: Environment, task: int) -> np.ndarray:
    """Moves from each state to the task's goal, by breadth-first search backwards over the
    dense true dynamics (the brute-force solver; -1 where no path)."""
    dense = env.transition_probabilities()
    distance = np.full(env.num_states, -1)
    queue: deque[int] = deque()
    for state in np.flatnonzero(env.tasks[task].reward > 0):
        distance[state] = 0
        queue.append(int(state))
    while queue:
        state = queue.popleft()
        for before in np.flatnonzero(dense[:, :, state].max(axis=1) > 0):
            if distance[before] < 0:
                distance[before] = distance[state] + 1
                queue.append(int(before))
    return distance


def _brute_force_optimum(env: Environment, task: int) -> float:
    """The optimal return counting r(s_1) ... r(s_H): reach the goal in d moves (at least 1,
    since the first reward is after one step) and stay, so H - max(d, 1) + 1."""
    distance = _distances(env, task)
    per_state = np.where(
        (distance >= 0) & (distance <= env.horizon),
        env.horizon - np.maximum(distance, 1) + 1,
        0,
    )
    return float(env.tasks[task].start @ per_state)


def _soft_reference(env: Environment, theta: np.ndarray, reward: np.ndarray) -> np.ndarray:
    """Equations (1)-(2) on the dense table, written out plainly."""
    dense = env.model.transitions(theta).dense()
    q = np.repeat(reward[:, None], env.num_actions, axis=1)
    for _ in range(env.horizon - 1):
        policy = np.exp(q - q.max(axis=1, keepdims=True))
        policy /= policy.sum(axis=1, keepdims=True)
        q = reward[:, None] + dense @ (policy * q).sum(axis=1)
    return q


PROPERTY_SETTINGS = settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)


@pytest.mark.parametrize("maps", [navigation_maps(), gravity_maps(), farming_maps()])
@PROPERTY_SETTINGS
@given(data=st.data())
def test_random_maps_checks_agree_with_brute_force(
    maps: st.SearchStrategy, data: st.DataObject
) -> None:  # type: ignore[type-arg]
    """On any map whose text and letters are right, the checks accept it exactly when every
    start cell reaches every goal within the horizon and no start is trapped, by an independent
    search; and a map they
    accept has rows that sum to one, its optimum equal to the brute force's, the planner equal
    to equations (1)-(2), and learners that save and load."""
    definition = data.draw(maps)
    problems = definition.problems()
    assert all(
        "cut off" in p.message or "reached" in p.message or "never reach" in p.message
        for p in problems
    ), problems
    # Trapped starts are refused exactly when the search finds a start with no way to the goal.
    accepting = replace(definition, max_trapped_start_share=1.0)
    if not accepting.problems():
        env = accepting.build()
        task = env.tasks[0]
        starts = (task.start > 0) | (task.study_start_distribution > 0)
        trapped = bool((_distances(env, 0)[starts] < 0).any())
        assert any("never reach" in p.message for p in problems) == trapped
    if problems:
        return
    env = definition.build()
    # No start of the simulations is trapped either.
    assert np.all(_distances(env, 0)[env.tasks[0].start > 0] >= 0)
    assert env.domain == definition.domain
    # Transition rows sum to one: the true table and the model's at a random theta.
    assert np.allclose(env.true_transitions.probabilities.sum(axis=2), 1.0)
    theta = np.random.default_rng(0).normal(size=env.model.num_parameters)
    assert np.allclose(env.model.probabilities(theta).sum(axis=2), 1.0)
    # Every start (a study start in gravity) reaches the goal within the horizon.
    distance = _distances(env, 0)
    starts = env.tasks[0].study_start_distribution > 0
    assert np.all((distance[starts] >= 0) & (distance[starts] <= env.horizon))
    # The planner's optimum is the brute force's.
    assert optimal_returns(env)[0] == pytest.approx(_brute_force_optimum(env, 0))
    reward = env.tasks[0].reward
    assert np.allclose(
        soft_value_iteration(env.model.transitions(theta), reward, 1.0, env.horizon),
        _soft_reference(env, theta, reward),
    )


@pytest.mark.parametrize("maps", [navigation_maps(), gravity_maps(), farming_maps()])
@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_random_maps_learners_save_and_load(maps: st.SearchStrategy, data: st.DataObject) -> None:  # type: ignore[type-arg]
    definition = data.draw(maps)
    if definition.problems():
        return
    env = definition.build()
    teacher = Teacher(env, seed=0)
    start = env.sample_start(0, np.random.default_rng(0), study=True)
    learner = make_learner("bam", env, alternations=1, cost_steps=2, dynamics_steps=2)
    for step in teacher.demonstration(0, start):
        learner.record_demonstration(0, *step)
    learner.update()
    restored = type(learner).from_state_dict(env, loads(dumps(learner.state_dict())))
    assert np.array_equal(restored.policy(0), learner.policy(0))
    assert np.array_equal(restored.theta, learner.theta)
    assert restored.updates == learner.updates == 1
    assert NUM_ACTIONS == env.num_actions
