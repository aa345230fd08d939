"""Each domain's rules, checked by hand on a few cells: the true dynamics (through ``step``,
which the parametrised tests tie to ``transition_probabilities()``) and the model rows."""

from __future__ import annotations

import numpy as np
import pytest

from server import domains
from server.domains.base import DOWN, LEFT, RIGHT, STAY, UP, Environment

NORTH, SOUTH, EAST, WEST = range(4)
NONE, PLOW, SPRINKLER, HARVESTER = range(4)
RNG = np.random.default_rng(0)


def step(
    env: Environment, cell: tuple[int, int], feature: int, action: int
) -> tuple[int, int, int]:
    """(row, column, feature) after one true step."""
    state = env.step(env.state_of(*cell, feature), action, RNG)
    return (*env.cell_of(state), env.feature_of(state))


def model_row(
    env: Environment, cell: tuple[int, int], feature: int, action: int, theta: np.ndarray
):  # type: ignore[no-untyped-def]
    """{(row, column, feature): model probability} of one (state, action), zero entries dropped."""
    state = env.state_of(*cell, feature)
    probabilities = env.model.probabilities(theta)[state, action]
    row: dict[tuple[int, int, int], float] = {}
    for successor, probability in zip(
        env.model.next_states[state, action], probabilities, strict=True
    ):
        if probability > 0:
            key = (*env.cell_of(int(successor)), env.feature_of(int(successor)))
            row[key] = row.get(key, 0.0) + float(probability)
    return row


def sigmoid(x: float) -> float:
    return 1.0 / (1.0 + np.exp(-x))


# -- navigation ---------------------------------------------------------------------------


def test_doorway_walls_block_and_doorway_passes() -> None:
    env = domains.make("doorway")
    assert step(env, (8, 5), 0, UP) == (7, 5, 0)  # the doorway
    assert step(env, (8, 4), 0, UP) == (8, 4, 0)  # wall at (7, 4)
    assert step(env, (8, 6), 0, UP) == (8, 6, 0)  # wall at (7, 6)
    assert step(env, (7, 5), 0, UP) == (6, 5, 0)
    assert step(env, (4, 2), 0, UP) == (4, 2, 0)  # wall at (3, 2)
    assert step(env, (4, 3), 0, UP) == (3, 3, 0)  # the wide opening of row 3
    assert step(env, (10, 0), 0, DOWN) == (10, 0, 0)  # off the grid
    assert step(env, (10, 0), 0, LEFT) == (10, 0, 0)
    assert step(env, (9, 9), 0, RIGHT) == (9, 10, 0)
    assert step(env, (9, 9), 0, STAY) == (9, 9, 0)


def test_wall_and_rooms_true_dynamics() -> None:
    wall = domains.make("wall")
    assert step(wall, (0, 2), 0, RIGHT) == (0, 2, 0)  # (0, 3) is a wall
    assert step(wall, (6, 2), 0, RIGHT) == (6, 3, 0)  # below the wall
    assert step(wall, (6, 4), 0, UP) == (6, 4, 0)
    two_rooms = domains.make("two-rooms")
    assert step(two_rooms, (2, 2), 0, RIGHT) == (2, 3, 0)  # the left room's door
    assert step(two_rooms, (1, 2), 0, RIGHT) == (1, 2, 0)
    assert step(two_rooms, (2, 6), 0, RIGHT) == (2, 6, 0)  # (2, 7) divides the rooms
    assert step(two_rooms, (2, 12), 0, LEFT) == (2, 11, 0)  # the right room's door
    three_rooms = domains.make("three-rooms")
    assert step(three_rooms, (8, 1), 0, RIGHT) == (8, 2, 0)
    assert step(three_rooms, (8, 5), 0, RIGHT) == (8, 5, 0)  # (8, 6) is a wall
    assert step(three_rooms, (4, 5), 0, DOWN) == (5, 5, 0)
    assert step(three_rooms, (5, 5), 0, DOWN) == (5, 5, 0)  # (6, 5) is a wall
    assert step(three_rooms, (4, 2), 0, UP) == (4, 2, 0)  # (3, 2) is a wall
    tutorial = domains.make("navigation-tutorial")
    assert step(tutorial, (5, 2), 0, RIGHT) == (5, 3, 0)  # into the box through (5, 3)
    assert step(tutorial, (4, 2), 0, RIGHT) == (4, 2, 0)


def test_navigation_model_rows() -> None:
    env = domains.make("doorway")
    model = env.model
    s, t = env.state_of(8, 4), env.state_of(7, 4)
    assert model.next_states[s, UP].tolist() == [t, s]
    assert model.const[s, UP].tolist() == [1.0, 0.0]
    assert model.coef[s, UP].tolist() == [-1.0, 1.0]
    assert model.index[s, UP].tolist() == [t, t]
    # STAY and off-grid moves: known, one real entry padded with a zero entry at s.
    corner = env.state_of(0, 0)
    for state, action in ((s, STAY), (corner, UP), (corner, LEFT)):
        assert model.next_states[state, action].tolist() == [state, state]
        assert model.const[state, action].tolist() == [1.0, 0.0]
        assert model.coef[state, action].tolist() == [0.0, 0.0]
    # Rows starting in a wall follow the same rule.
    w = env.state_of(7, 4)
    assert model.next_states[w, RIGHT].tolist() == [env.state_of(7, 5), w]
    theta = model.initial_parameters()
    assert model_row(env, (8, 4), 0, UP, theta) == pytest.approx(
        {(7, 4, 0): 1 - sigmoid(-3.0), (8, 4, 0): sigmoid(-3.0)}
    )
    theta = np.zeros(model.num_parameters)
    theta[env.state_of(7, 4)] = 2.0
    assert model_row(env, (8, 4), 0, UP, theta) == pytest.approx(
        {(7, 4, 0): 1 - sigmoid(2.0), (8, 4, 0): sigmoid(2.0)}
    )
    assert model_row(env, (0, 0), 0, UP, theta) == {(0, 0, 0): 1.0}


# -- gravity --------------------------------------------------------------------------------


def test_flip_colours_set_gravity() -> None:
    """As in the authors' dynamics: entering a coloured cell changes nothing yet; any action
    taken from it (STAY included) first sets the colour's gravity, and the move is judged
    against that gravity."""
    env = domains.make("flip")
    assert step(env, (1, 1), NORTH, UP) == (0, 1, NORTH)  # entering orange
    assert step(env, (0, 1), NORTH, STAY) == (0, 1, SOUTH)  # orange sets south
    assert step(env, (0, 1), NORTH, DOWN) == (1, 1, SOUTH)  # south permits DOWN
    assert step(env, (0, 1), NORTH, UP) == (0, 1, SOUTH)  # off the grid
    assert step(env, (0, 4), WEST, RIGHT) == (0, 5, SOUTH)
    assert step(env, (0, 0), EAST, RIGHT) == (0, 1, EAST)
    assert step(env, (8, 1), SOUTH, DOWN) == (9, 1, SOUTH)  # entering green
    assert step(env, (9, 1), SOUTH, UP) == (8, 1, NORTH)  # green sets north
    assert step(env, (9, 1), SOUTH, DOWN) == (9, 1, NORTH)  # north forbids DOWN
    assert step(env, (9, 7), WEST, RIGHT) == (9, 7, WEST)  # west forbids RIGHT
    assert step(env, (9, 7), NORTH, RIGHT) == (9, 8, NORTH)


def test_gravity_forbids_moving_against_it() -> None:
    env = domains.make("flip")
    forbidden = {NORTH: DOWN, SOUTH: UP, EAST: LEFT, WEST: RIGHT}
    targets = {UP: (3, 5), DOWN: (5, 5), LEFT: (4, 4), RIGHT: (4, 6)}
    for gravity in range(4):
        for action, target in targets.items():
            expected = (4, 5, gravity) if action == forbidden[gravity] else (*target, gravity)
            assert step(env, (4, 5), gravity, action) == expected


def test_choices_purple_sets_north() -> None:
    env = domains.make("choices")
    assert step(env, (1, 13), EAST, UP) == (0, 13, EAST)  # entering purple
    assert step(env, (0, 13), EAST, DOWN) == (0, 13, NORTH)  # purple sets north: no DOWN
    assert step(env, (0, 13), SOUTH, LEFT) == (0, 12, NORTH)
    assert step(env, (0, 10), WEST, DOWN) == (1, 10, SOUTH)  # orange
    assert step(env, (0, 1), SOUTH, RIGHT) == (0, 2, NORTH)  # green
    assert step(env, (3, 1), NORTH, LEFT) == (3, 0, NORTH)  # the goal cell A is plain


def test_gravity_model_rows() -> None:
    env = domains.make("choices")
    model = env.model
    # Groups: orange, green, purple. From purple (0, 13), DOWN: one successor per gravity g,
    # staying where g forbids DOWN (north).
    state = env.state_of(0, 13, EAST)
    assert model.next_states[state, DOWN].tolist() == [
        env.state_of(0, 13, NORTH),
        env.state_of(1, 13, SOUTH),
        env.state_of(1, 13, EAST),
        env.state_of(1, 13, WEST),
    ]
    assert model.index[state, DOWN].tolist() == [8, 9, 10, 11]
    assert model.const[state, DOWN].tolist() == [0.0] * 4
    assert model.coef[state, DOWN].tolist() == [1.0] * 4
    assert model_row(env, (0, 13), EAST, STAY, model.initial_parameters()) == pytest.approx(
        {(0, 13, g): 0.25 for g in range(4)}
    )
    theta = np.zeros(12)
    theta[4:8] = [2.0, 0.0, -1.0, 0.5]  # green
    softmax = np.exp(theta[4:8]) / np.exp(theta[4:8]).sum()
    # From green (0, 1), LEFT: east forbids it.
    expected = {(0, 0, g): softmax[g] for g in range(4) if g != EAST}
    expected[(0, 1, EAST)] = softmax[EAST]
    assert model_row(env, (0, 1), SOUTH, LEFT, theta) == pytest.approx(expected)
    # Plain cells keep the gravity, forbidden moves stay, entering a colour changes nothing:
    # known to the learner.
    assert model_row(env, (2, 5), EAST, RIGHT, theta) == {(2, 6, EAST): 1.0}
    assert model_row(env, (2, 5), EAST, LEFT, theta) == {(2, 5, EAST): 1.0}
    assert model_row(env, (1, 13), EAST, UP, theta) == {(0, 13, EAST): 1.0}
    plain = env.state_of(2, 5, EAST)
    assert model.coef[plain].tolist() == [[0.0] * 4] * 5


# -- farming --------------------------------------------------------------------------------


def test_two_fields_machines_and_terrain() -> None:
    env = domains.make("two-fields")
    # Soil at (2, 2), reached from the dirt cell (2, 3).
    assert step(env, (2, 3), PLOW, LEFT) == (2, 2, PLOW)
    assert step(env, (2, 3), HARVESTER, LEFT) == (2, 3, HARVESTER)
    assert step(env, (2, 3), SPRINKLER, LEFT) == (2, 3, SPRINKLER)
    assert step(env, (2, 3), NONE, LEFT) == (2, 3, NONE)
    # Grown crops at (5, 2), next to the harvester at (5, 4).
    assert step(env, (5, 3), HARVESTER, LEFT) == (5, 2, HARVESTER)
    assert step(env, (5, 3), PLOW, LEFT) == (5, 3, PLOW)
    # Inside a field the same rule holds; leaving onto dirt always succeeds.
    assert step(env, (1, 1), PLOW, DOWN) == (2, 1, PLOW)
    assert step(env, (1, 1), HARVESTER, DOWN) == (1, 1, HARVESTER)
    assert step(env, (1, 2), HARVESTER, RIGHT) == (1, 3, HARVESTER)
    assert step(env, (6, 1), NONE, DOWN) == (7, 1, NONE)


def test_machines_are_picked_up_and_swapped() -> None:
    env = domains.make("two-fields")
    assert step(env, (3, 9), NONE, RIGHT) == (3, 10, PLOW)  # the plow at (3, 10)
    assert step(env, (2, 3), PLOW, RIGHT) == (2, 4, SPRINKLER)  # swapped at the sprinkler
    assert step(env, (2, 5), HARVESTER, LEFT) == (2, 4, SPRINKLER)
    assert step(env, (4, 4), SPRINKLER, DOWN) == (5, 4, HARVESTER)
    # The machine stays on its cell: leaving and stepping back on picks it up again.
    assert step(env, (2, 4), SPRINKLER, UP) == (1, 4, SPRINKLER)
    assert step(env, (1, 4), PLOW, DOWN) == (2, 4, SPRINKLER)
    # STAY on a machine's cell keeps what is carried.
    assert step(env, (3, 10), HARVESTER, STAY) == (3, 10, HARVESTER)


def test_three_fields_and_tutorial_terrains() -> None:
    three = domains.make("three-fields")
    assert step(three, (5, 3), SPRINKLER, LEFT) == (5, 2, SPRINKLER)  # immature crops
    assert step(three, (5, 3), PLOW, LEFT) == (5, 3, PLOW)
    assert step(three, (1, 7), PLOW, RIGHT) == (1, 8, PLOW)  # the decoy soil field
    assert step(three, (5, 8), NONE, RIGHT) == (5, 9, PLOW)
    tutorial = domains.make("farming-tutorial")
    assert step(tutorial, (0, 5), SPRINKLER, DOWN) == (1, 5, SPRINKLER)  # grass
    assert step(tutorial, (0, 5), PLOW, DOWN) == (0, 5, PLOW)
    assert step(tutorial, (0, 9), HARVESTER, DOWN) == (1, 9, HARVESTER)  # crops
    assert step(tutorial, (0, 9), SPRINKLER, DOWN) == (0, 9, SPRINKLER)
    assert step(tutorial, (9, 6), NONE, UP) == (8, 6, HARVESTER)


def test_farming_model_rows() -> None:
    env = domains.make("two-fields")
    model = env.model
    # Parameters: per machine, dirt, soil, grass, crops.
    for machine, index in ((PLOW, 1), (SPRINKLER, 5), (HARVESTER, 9)):  # onto soil
        state = env.state_of(2, 3, machine)
        assert model.next_states[state, LEFT].tolist() == [env.state_of(2, 2, machine), state]
        assert model.const[state, LEFT].tolist() == [0.0, 1.0]
        assert model.coef[state, LEFT].tolist() == [1.0, -1.0]
        assert model.index[state, LEFT].tolist() == [index, index]
        assert model.outcomes[state, LEFT].tolist() == [1, -1]
    crops = env.state_of(5, 3, HARVESTER)
    assert model.index[crops, LEFT].tolist() == [11, 11]  # harvester x crops
    theta = np.zeros(12)
    theta[0:4] = [0.3, 1.0, -1.0, 0.5]  # plow over dirt, soil, grass, crops
    softmax = np.exp(theta[0:4]) / np.exp(theta[0:4]).sum()
    assert model_row(env, (2, 3), PLOW, LEFT, theta) == pytest.approx(
        {(2, 2, PLOW): softmax[1], (2, 3, PLOW): 1 - softmax[1]}
    )
    assert model_row(env, (5, 3), PLOW, LEFT, theta) == pytest.approx(
        {(5, 2, PLOW): softmax[3], (5, 3, PLOW): 1 - softmax[3]}
    )
    # Known outcomes: carrying nothing never enters a field; dirt and machines always succeed.
    assert model_row(env, (2, 3), NONE, LEFT, theta) == {(2, 3, NONE): 1.0}
    assert model_row(env, (2, 3), PLOW, RIGHT, theta) == {(2, 4, SPRINKLER): 1.0}
    assert model_row(env, (1, 2), HARVESTER, RIGHT, theta) == {(1, 3, HARVESTER): 1.0}
    # STAY on a field carrying a machine: the same state either way.
    assert model_row(env, (2, 2), PLOW, STAY, theta) == pytest.approx({(2, 2, PLOW): 1.0})


def test_farming_starts_carry_nothing_on_free_dirt() -> None:
    env = domains.make("two-fields")
    # 96 cells, 8 field cells and 3 machines.
    for task in env.tasks:
        support = np.flatnonzero(task.start)
        assert len(support) == 85
        assert all(env.feature_of(int(s)) == NONE for s in support)
    assert env.state_of(3, 10, NONE) not in set(np.flatnonzero(env.tasks[0].start).tolist())
    assert env.tasks[0].reward.sum() == 16  # 4 cells x 4 machines carried
