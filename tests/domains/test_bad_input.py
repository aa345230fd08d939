"""Bad input raises a clear ValueError instead of propagating garbage."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from server import domains
from server.domains import farming, gravity, navigation
from server.domains.base import DOWN, LEFT, RIGHT, STAY, UP, all_finite, check_finite
from server.domains.grid import Region, load_map, parse_map

NORTH, EAST = 0, 2
PLOW = 1


@pytest.mark.parametrize("name", ["nope", "Doorway", "", "flip ", None, 3])
def test_unknown_name_lists_valid_names(name: object) -> None:
    with pytest.raises(ValueError, match="unknown environment") as error:
        domains.make(name)  # type: ignore[arg-type]
    for valid in domains.NAMES:
        assert valid in str(error.value)
    with pytest.raises(ValueError, match="valid names"):
        domains.domain_of(str(name))


@pytest.mark.parametrize("name", domains.NAMES)
def test_state_of_out_of_range(name: str) -> None:
    env = domains.make(name)
    for cell in ((-1, 0), (0, -1), (env.height, 0), (0, env.width)):
        with pytest.raises(ValueError, match="outside"):
            env.state_of(*cell)
    for feature in (-1, env.num_features):
        with pytest.raises(ValueError, match="feature"):
            env.state_of(0, 0, feature)
    last = env.state_of(env.height - 1, env.width - 1, env.num_features - 1)
    assert last == env.num_states - 1


@pytest.mark.parametrize("name", domains.NAMES)
def test_checks_reject_bad_values(name: str) -> None:
    env = domains.make(name)
    bad_common: list[object] = [-1, 1.0, True, False, "1", None, np.float64(0.0)]
    for check, size in (
        (env.check_state, env.num_states),
        (env.check_action, env.num_actions),
        (env.check_task, len(env.tasks)),
    ):
        for value in [*bad_common, size]:
            with pytest.raises(ValueError):
                check(value)  # type: ignore[arg-type]
        # NumPy integers are accepted and returned as Python ints.
        last: Any = np.int64(size - 1)
        assert check(last) == size - 1 and type(check(last)) is int
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError):
        env.step(env.num_states, STAY, rng)
    with pytest.raises(ValueError):
        env.step(0, 5, rng)
    with pytest.raises(ValueError):
        env.sample_start(len(env.tasks), rng)
    with pytest.raises(ValueError):
        env.is_goal(0, -1)


def test_impossible_transitions_rejected() -> None:
    cases = [
        # A move cannot jump two cells or go sideways, STAY cannot move.
        ("doorway", (9, 5, 0), RIGHT, (9, 7, 0)),
        ("doorway", (9, 5, 0), UP, (9, 6, 0)),
        ("doorway", (9, 5, 0), STAY, (8, 5, 0)),
        # Gravity: a plain cell keeps the gravity; a forbidden move stays.
        ("flip", (4, 4, NORTH), RIGHT, (4, 5, EAST)),
        ("flip", (4, 4, EAST), LEFT, (4, 3, EAST)),
        # Farming: carrying nothing never enters a field; a machine is always picked up.
        ("two-fields", (2, 3, 0), LEFT, (2, 2, 0)),
        ("two-fields", (2, 3, PLOW), RIGHT, (2, 4, PLOW)),
    ]
    for name, (row, column, feature), action, (row2, column2, feature2) in cases:
        env = domains.make(name)
        s, s2 = env.state_of(row, column, feature), env.state_of(row2, column2, feature2)
        observed = np.array([[env.state_of(0, 0), STAY, env.state_of(0, 0)], [s, action, s2]])
        with pytest.raises(ValueError, match="impossible"):
            env.model.transition_log_likelihood(env.model.initial_parameters(), observed)


@pytest.mark.parametrize("name", ["wall", "choices", "three-fields"])
def test_observed_out_of_range(name: str) -> None:
    env = domains.make(name)
    theta = env.model.initial_parameters()
    for row in ([env.num_states, STAY, 0], [-1, STAY, 0], [0, STAY, env.num_states]):
        with pytest.raises(ValueError, match="state out of range"):
            env.model.transition_log_likelihood(theta, np.array([row]))
    for action in (-1, 5):
        with pytest.raises(ValueError, match="action out of range"):
            env.model.transition_log_likelihood(theta, np.array([[0, action, 0]]))
    value, gradient = env.model.transition_log_likelihood(theta, np.zeros((0, 3), dtype=int))
    assert value == 0.0 and np.array_equal(gradient, np.zeros(env.model.num_parameters))


@pytest.mark.parametrize("name", ["doorway", "flip", "two-fields"])
def test_bad_parameters(name: str) -> None:
    env = domains.make(name)
    model = env.model
    good = model.initial_parameters()
    observed = np.array([[0, UP, 0]])
    weights = np.zeros(model.next_states.shape)
    for bad_value in (np.nan, np.inf, -np.inf):
        theta = good.copy()
        theta[-1] = bad_value
        for call in (
            lambda t: model.probabilities(t),
            lambda t: model.transitions(t),
            lambda t: model.pullback(t, weights),
            lambda t: model.transition_log_likelihood(t, observed),
        ):
            with pytest.raises(ValueError, match="NaN or infinite"):
                call(theta)
    # The model knows the last theta it found finite (a learner's step checks one theta three
    # times): a theta changed in place after passing, or a restricted model's, is checked again.
    theta = good.copy()
    model.probabilities(theta)
    theta[0] = np.nan
    for call in (
        lambda t: model.probabilities(t),
        lambda t: model.pullback(t, weights),
        lambda t: model.transition_log_likelihood(t, observed),
        lambda t: model.restricted(np.arange(env.num_states)).probabilities(t),
    ):
        with pytest.raises(ValueError, match="NaN or infinite"):
            call(theta)
    for theta in (good[:-1], np.append(good, 0.0), good.reshape(1, -1), np.asarray(0.0)):
        with pytest.raises(ValueError, match="shape"):
            model.probabilities(theta)
        with pytest.raises(ValueError, match="shape"):
            model.transition_log_likelihood(theta, observed)
    with pytest.raises(ValueError, match="shape"):
        model.pullback(good, weights[:, :, :1])
    with pytest.raises(ValueError, match="shape"):
        model.pullback_dense(good, np.zeros((env.num_states, 5, env.num_states - 1)))


def test_family_builders_reject_foreign_maps() -> None:
    with pytest.raises(ValueError, match="unknown character 'o'"):
        navigation.build("x", load_map("flip"))
    with pytest.raises(ValueError, match="unknown character '#'"):
        gravity.build("x", load_map("doorway"))
    with pytest.raises(ValueError, match="unknown character"):
        farming.build("x", load_map("wall"))


GOOD_MAP = """# a comment
task: A
start: rows 1-2
    0123
  0 A...
  1 .#..
  2 ....
"""


def test_parse_map() -> None:
    grid_map = parse_map("x", GOOD_MAP)
    assert grid_map.grid == ("A...", ".#..", "....")
    assert (grid_map.height, grid_map.width) == (3, 4)
    assert grid_map.tasks[0].name == "A" and grid_map.tasks[0].goal_cells == ((0, 0),)
    assert grid_map.start == Region(range(1, 3), None)
    assert (2, 3) in grid_map.start and (0, 3) not in grid_map.start


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (GOOD_MAP.replace("    0123", "    0124"), "column header"),
        (GOOD_MAP.replace("  1 .#..", "  1 .#."), "wide"),
        (GOOD_MAP.replace("  2 ....", "  3 ...."), "expected row 2"),
        (GOOD_MAP.replace("start:", "begin:"), "unknown header key"),
        (GOOD_MAP.replace("task: A", "task: Z"), "no goal cell"),
        (GOOD_MAP.replace("task: A", "task: A\ntask: A"), "distinct names"),
        (GOOD_MAP.replace("rows 1-2", "rows 2-1"), "empty range"),
        (GOOD_MAP.replace("rows 1-2", "lines 1-2"), "cannot read region"),
        (GOOD_MAP.replace("rows 1-2", "rows 1, rows 2"), "twice"),
        (GOOD_MAP + "study-start B: rows 0\n", "expected row 3"),
        (GOOD_MAP.replace("start:", "study-start B:"), "unknown tasks"),
        (GOOD_MAP.replace("# a comment", "a comment"), "expected 'key: value'"),
        ("task: A\n", "no grid"),
    ],
)
def test_parse_map_errors(text: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        parse_map("x", text)


@pytest.mark.parametrize(
    ("values", "finite"),
    [
        ([1e308, 1e308], True),
        ([], True),
        ([1.0, np.nan], False),
        ([np.inf, -np.inf], False),  # the sum is NaN
        ([-1e308, -1e308, np.inf], False),
        ([[0.5, 2.0], [3.0, -np.inf]], False),
    ],
)
def test_all_finite_refuses_any_nan_or_infinity(values, finite) -> None:  # type: ignore[no-untyped-def]
    array = np.array(values, dtype=np.float64)
    assert all_finite(array) is finite
    if not finite:
        with pytest.raises(ValueError, match="NaN or infinite"):
            check_finite("x", array)
    else:
        assert check_finite("x", array) is array


def test_a_possible_transition_whose_probability_rounds_to_0_is_not_impossible() -> None:
    """Farming's logits reach +-50 (the authors' clip), where a machine works with probability
    1 - 1e-43, which is 1: a failed move then had probability 0, and a participant's update
    failed ("impossible"). It counts as the least normal probability instead; a transition the
    model space can never give stays an error."""
    env = domains.make("two-fields")
    model = env.model
    # Entry 55: state 5, DOWN, staying put (a failure), probability 1 - p[1]; theta[1] is the
    # logit of p[1] against theta[0], theta[2], theta[3].
    theta = np.full(model.num_parameters, -50.0)
    theta[1] = 50.0
    assert model.primitives(theta)[1] == 1.0
    failure = np.array([[5, DOWN, 5]])
    for rule in ("exact", "authors"):
        value, gradient = model.transition_log_likelihood(theta, failure, rule=rule)
        assert value == pytest.approx(np.log(np.finfo(np.float64).tiny))
        assert np.all(np.isfinite(gradient)) and np.all(np.abs(gradient) < 1.0)
    # Beside other transitions, their terms are as before to the last bit.
    others = np.array([[env.state_of(0, 0), STAY, env.state_of(0, 0)]])
    alone, alone_gradient = model.transition_log_likelihood(theta, others)
    both, both_gradient = model.transition_log_likelihood(theta, np.vstack([others, failure]))
    assert both == alone + np.log(np.finfo(np.float64).tiny)
    assert np.array_equal(both_gradient, alone_gradient)
    # Carrying nothing never enters a field, whatever theta.
    with pytest.raises(ValueError, match="impossible"):
        model.transition_log_likelihood(
            theta, np.array([[env.state_of(2, 3, 0), LEFT, env.state_of(2, 2, 0)]])
        )
