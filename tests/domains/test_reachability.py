"""Traps (server.domains.reachability): the states from which a task's goal can never be
reached. A tiny map worked out by hand, the map a study once shipped with 617 of 2,000
simulation starts trapped, and every built-in environment."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from server import domains
from server.domains import gravity
from server.domains.base import Environment
from server.domains.gravity import GRAVITIES
from server.domains.grid import read_map
from server.domains.reachability import describe, reaches_goal, trapped_states
from server.domains.spec import EnvironmentSpec

# 9 wide x 7 high, every start on the bottom row (row 6), no colour on it: with gravity south
# a start there can never move up, and the last column with gravity east (the first with
# gravity west) never meets a colour either.
NEWCOMER = """task: Well = W
task: Tower = T
start: rows 6
gravity of orange: north
gravity of green: south
    012345678
  0 ..o.T..o.
  1 .........
  2 .........
  3 .g..W..g.
  4 .........
  5 .........
  6 .........
"""

# Goal (0, 0); orange (0, 2) sets gravity east, which forbids moving left.
TINY = """task: A
start: {start}
gravity of orange: east
    012
  0 A.o
  1 ...
"""


def states(env: Environment, *cells: tuple[int, int, str]) -> list[int]:
    return sorted(env.state_of(row, column, GRAVITIES.index(g)) for row, column, g in cells)


def tiny(start: str) -> Environment:
    """Built by the domain without the study's checks (its orange cell is cut off)."""
    grid_map, problems = read_map("tiny", TINY.format(start=start))
    assert grid_map is not None and not problems
    return gravity.build("tiny", grid_map)


def test_a_tiny_map_worked_out_by_hand() -> None:
    env = tiny("anywhere")
    traps = trapped_states(env, 0)
    # East anywhere right of column 0 cannot move left again (row 1's first cell can go up);
    # every gravity on the orange cell turns east; south in row 1 can never go up.
    assert list(traps.starts) == states(
        env,
        (0, 1, "east"), (1, 1, "east"), (1, 2, "east"),
        *((0, 2, gravity) for gravity in GRAVITIES),
        (1, 0, "south"), (1, 1, "south"), (1, 2, "south"),
    )  # fmt: skip
    assert (traps.start_states, traps.start_share) == (24, pytest.approx(10 / 24))
    assert traps.study_start_share == 0  # the user study starts only where the goal is reached
    assert len(traps.reachable) == 0 and traps.reachable_states == 24  # every state starts


def test_trapped_states_reachable_from_the_starts() -> None:
    env = tiny("rows 0, columns 1")
    traps = trapped_states(env, 0)
    assert list(traps.starts) == states(env, (0, 1, "east"))
    # Right onto orange keeps the gravity until the agent acts there; south drops to row 1.
    assert list(traps.reachable) == states(
        env,
        (0, 2, "north"), (0, 2, "south"), (0, 2, "east"), (1, 2, "east"), (1, 1, "east"),
        (1, 0, "south"), (1, 1, "south"), (1, 2, "south"),
    )  # fmt: skip
    assert traps.start_share == pytest.approx(0.25)
    assert describe(env, int(traps.starts[0])) == "(row 0, column 1, gravity east)"


def test_the_newcomers_map_is_refused_with_its_trapped_starts_named() -> None:
    definition = EnvironmentSpec("newcomer", "gravity", NEWCOMER)
    problems = {problem.message.split(":")[0]: problem for problem in definition.problems()}
    assert set(problems) == {"task 'Well'", "task 'Tower'"}
    well = problems["task 'Well'"]
    assert (well.line, well.column) == (13, 5)  # row 6, column 0
    assert "11 of its 36 start states (30.6% of the simulations' start probability)" in (
        well.message
    )
    assert (
        "(gravity south at row 6, columns 0-8; gravity east at row 6, column 8; "
        "gravity west at row 6, column 0)" in well.message
    )
    assert "max_trapped_start_share = 0.31" in well.message
    # Accepting the larger of the two shares builds it; the simulations then waste 617 of
    # 2,000 of the first task's episodes, as the study that shipped it did.
    assert replace(definition, max_trapped_start_share=0.36).problems() != []
    env = replace(definition, max_trapped_start_share=0.37).build()
    reaches = reaches_goal(env, 0)
    rng = np.random.default_rng(0)
    assert sum(not reaches[env.sample_start(0, rng)] for _ in range(2000)) == 617
    traps = trapped_states(env, 0)
    assert all(env.cell_of(int(state))[0] == 6 for state in traps.starts)
    assert len(traps.reachable) == 61  # the top rows under north, say, once orange acts


def test_a_share_outside_0_to_1_is_a_problem() -> None:
    problems = EnvironmentSpec(
        "newcomer", "gravity", NEWCOMER, max_trapped_start_share=1.5
    ).problems()
    assert any(
        "max_trapped_start_share 1.5 is not a share from 0 to 1" in p.message for p in problems
    )


# The paper's gravity maps start their simulations in every gravity, as the authors' did,
# including these few trapped states (the last column under east for a goal on the left, the
# first under west for one on the right); the user study starts none of them.
TRAPPED_BY_DESIGN = {
    ("flip", "A"): ("east", 9, 10),
    ("flip", "B"): ("west", 0, 10),
    ("gravity-tutorial", "A"): ("east", 9, 10),
    ("gravity-tutorial", "B"): ("west", 0, 10),
    ("choices", "A"): ("east", 14, 4),
    ("choices", "B"): ("west", 0, 4),
}


@pytest.mark.parametrize("name", domains.NAMES)
def test_the_built_in_environments_have_no_trapped_start_but_the_papers_own(name: str) -> None:
    env = domains.make(name)
    for number, task in enumerate(env.tasks):
        traps = trapped_states(env, number)
        assert traps.study_start_share == 0
        assert len(traps.reachable) == 0
        expected = TRAPPED_BY_DESIGN.get((name, task.name))
        if expected is None:
            assert len(traps.starts) == 0, traps.named(env, traps.starts)
            continue
        gravity, column, count = expected
        assert len(traps.starts) == count
        assert (
            traps.named(env, traps.starts)
            == f"gravity {gravity} at column {column}, rows 0-{count - 1}"
        )
