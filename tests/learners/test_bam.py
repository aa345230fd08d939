"""BAM's defining behaviour (section 3.1): from demonstrations alone it learns dynamics the
teacher knows but never showed, here the walls beside the doorway of the doorway environment,
which model-based IRL (fitting the dynamics to observed transitions only) cannot."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from server import domains, learners
from server.teacher import Teacher
from tests.learners._support import demonstrate_round, is_failed_move

INITIAL_FAILURE = 1.0 / (1.0 + np.exp(3.0))  # sigmoid(-3) = 0.047: cells presumed free
DOORWAY, LEFT_WALL, RIGHT_WALL = (7, 5), (7, 4), (7, 6)
ROUNDS = 5


def failure_probability(learner: Any, cell: tuple[int, int]) -> float:
    """The learned probability that a move into ``cell`` fails (navigation's model space)."""
    env = learner.env
    index = cell[0] * env.width + cell[1]
    assert env.model.parameter_names[index] == f"fail({cell[0]},{cell[1]})"
    return float(1.0 / (1.0 + np.exp(-learner.theta[index])))


def taught(name: str, **settings: Any) -> tuple[Any, list[tuple[int, int, int, int]]]:
    env = domains.make("doorway")
    learner = learners.make(name, env, seed=0, **settings)
    teacher = Teacher(env, seed=0)
    rng = np.random.default_rng(0)
    rows = []
    for _ in range(ROUNDS):
        rows += demonstrate_round(learner, env, teacher, rng)
        learner.update()
    return learner, rows


def test_the_doorway_layout() -> None:
    env = domains.make("doorway")
    walls = {tuple(cell) for cell in env.layout["walls"]}
    assert DOORWAY not in walls and LEFT_WALL in walls and RIGHT_WALL in walls
    assert failure_probability(learners.make("bam", env), LEFT_WALL) == pytest.approx(
        0.0474, abs=1e-4
    )


@pytest.mark.slow
def test_bam_puts_the_doorway_where_it_is() -> None:
    learner, rows = taught("bam")
    env = learner.env
    # The teacher never walked into a wall: no recorded move failed, and no demonstration
    # even tried to enter the cells beside the doorway.
    assert not any(
        is_failed_move(state, action, next_state) for _, state, action, next_state in rows
    )
    observed = learner.data.observed_transitions()
    assert not any(is_failed_move(*map(int, row)) for row in observed)
    doorway = env.state_of(*DOORWAY)
    assert any(next_state == doorway for _, _, _, next_state in rows)
    # Yet BAM believes the doorway passable and its neighbours blocked.
    assert failure_probability(learner, DOORWAY) < INITIAL_FAILURE / 2
    for wall in (LEFT_WALL, RIGHT_WALL):
        assert failure_probability(learner, wall) > 0.5, wall


@pytest.mark.slow
def test_model_based_irl_cannot_learn_unobserved_walls() -> None:
    """Model-based IRL fits T_theta to observed transitions only: the wall cells beside the
    doorway, never entered or bumped into, keep their prior belief."""
    learner, _ = taught("model-based")
    assert failure_probability(learner, DOORWAY) < INITIAL_FAILURE / 2
    for wall in (LEFT_WALL, RIGHT_WALL):
        assert failure_probability(learner, wall) == pytest.approx(INITIAL_FAILURE, abs=1e-6)


@pytest.mark.slow
def test_default_optimiser_reaches_at_least_the_alternatives_likelihood() -> None:
    """The default optimiser reaches at least the value of equation (5) that the other
    shipped optimiser reaches on the same data: the measured reason it is the default (on
    doorway, momentum about -165.3 against L-BFGS-B capped at 40 evaluations about -169.8)."""
    default_name = learners.learner_class("bam").default_settings["optimizer"]
    other_name = {"momentum": "lbfgs", "lbfgs": "momentum"}[default_name]
    default, _ = taught("bam")
    other, _ = taught("bam", optimizer=other_name)
    assert default.objective()[0] >= other.objective()[0] - 1e-6 * abs(other.objective()[0])
