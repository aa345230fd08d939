"""Gravity: the agent cannot move against the current gravity, and a coloured cell sets the
gravity to the direction that colour maps to. The learner sees colours, not directions: its
model is one softmax over the four gravities per colour, with the paper authors' prior N(0, 1)
on the logits, clipped to +-50.

States are (cell, gravity) with gravities north, south, east, west. Gravity NORTH forbids
moving DOWN, SOUTH forbids UP, EAST forbids LEFT and WEST forbids RIGHT. As in the authors'
dynamics, a colour acts when the agent acts from its cell: any action taken on a coloured cell
(STAY included) first sets the gravity, and the move is then judged against the new gravity,
so the row has four model successors, one per gravity g', each with probability
softmax(theta[colour])[g']; entering a coloured cell changes nothing yet. On a plain cell,
forbidden moves, moves off the grid and STAY leave the agent where it is, and permitted moves
keep the gravity (known). There are no walls.

Simulations start anywhere, in any gravity, as the authors' do (a few such states can never
reach the goal); a participant of the study starts only where the goal can be reached.
"""

from __future__ import annotations

import numpy as np

from server.domains.base import (
    DOWN,
    LEFT,
    NUM_ACTIONS,
    RIGHT,
    UP,
    Environment,
    SoftmaxRowsModel,
    Task,
)
from server.domains.drawing import drawing
from server.domains.grid import (
    GridMap,
    Successor,
    TransitionTable,
    can_reach,
    empty_layout,
    goal_reward,
    known,
    make_environment,
    target_cell,
    uniform,
)

DOMAIN = "gravity"
GRAVITIES: tuple[str, ...] = ("north", "south", "east", "west")
NORTH, SOUTH, EAST, WEST = range(4)
# The move each gravity forbids.
FORBIDDEN: dict[int, int] = {NORTH: DOWN, SOUTH: UP, EAST: LEFT, WEST: RIGHT}
# Map letter -> colour, in the order the model's softmax rows take them.
COLOURS: dict[str, str] = {"o": "orange", "g": "green", "p": "purple"}
PLAIN = "."
TRUE_LOGIT = 30.0  # softmax(+30 against -30) is within 1e-26 of one-hot
PRIOR_SD = 1.0  # the authors' N(0, 1) on the logits
PARAMETER_BOUND = 50.0  # the authors clip the logits here after every update


def horizon(height: int, width: int) -> int:
    return 4 * (width + height)


def build(
    name: str,
    grid_map: GridMap,
    horizon_steps: int | None = None,
    colours: dict[str, str] | None = None,
    palette: dict[str, str] | None = None,
) -> Environment:
    """The environment of a gravity map. ``horizon_steps``: the horizon, unless the domain's
    own, 4 * (width + height); ``colours``: {map letter: colour} (``COLOURS`` unless given),
    whose order is the order of the model's softmax rows; ``palette``: {colour: "#rrggbb"} for
    colours the page does not know.

    One function, as the other domains' ``build``: the map's colours, the rule's transitions,
    the model, the tasks and the layout, in the order the environment is made of them, each
    reading the names the step before defined."""
    colours = dict(COLOURS) if colours is None else colours
    steps = horizon_steps or horizon(grid_map.height, grid_map.width)
    grid_map.check_characters(PLAIN + "".join(colours))
    height, width = grid_map.height, grid_map.width
    num_features = len(GRAVITIES)
    num_states = height * width * num_features
    colour_of_cell = {
        cell: colours[grid_map.char(cell)]
        for cell in grid_map.cells()
        if grid_map.char(cell) in colours
    }
    # Softmax rows: the colours present, in the order of ``colours`` (orange, green, purple).
    groups = [colour for colour in colours.values() if colour in colour_of_cell.values()]
    mapping = grid_map.gravity_of_colour
    if set(mapping) != set(groups) or not set(mapping.values()) <= set(GRAVITIES):
        raise ValueError(
            f"map {name!r}: give one gravity among {GRAVITIES} for each of {groups}; got {mapping}"
        )

    def state_of(cell: tuple[int, int], gravity: int) -> int:
        return (cell[0] * width + cell[1]) * num_features + gravity

    table = TransitionTable(num_states, num_features)
    for cell in grid_map.cells():
        for gravity in range(num_features):
            state = state_of(cell, gravity)
            for action in range(NUM_ACTIONS):
                target = target_cell(cell, action, height, width)
                if cell in colour_of_cell:
                    colour = colour_of_cell[cell]
                    group = groups.index(colour)
                    true_gravity = GRAVITIES.index(mapping[colour])
                    table.set(
                        state,
                        action,
                        [
                            Successor(
                                state_of(
                                    cell if target is None or action == FORBIDDEN[new] else target,
                                    new,
                                ),
                                0.0,
                                1.0,
                                group * num_features + new,
                                float(new == true_gravity),
                            )
                            for new in range(num_features)
                        ],
                    )
                elif target is None or action == FORBIDDEN[gravity]:
                    table.set(state, action, known(state))
                else:
                    table.set(state, action, known(state_of(target, gravity)))
    model = SoftmaxRowsModel(
        **table.model_arrays(),
        num_parameters=len(groups) * num_features,
        initial_value=0.0,
        parameter_names=[f"{colour}->{gravity}" for colour in groups for gravity in GRAVITIES],
        groups=len(groups),
        choices=num_features,
        prior_sd=PRIOR_SD,
        parameter_bound=PARAMETER_BOUND,
    )

    candidates = [
        state_of(cell, gravity)
        for cell in grid_map.cells()
        if cell in grid_map.start
        for gravity in range(num_features)
    ]
    true_transitions = table.true_transitions()
    if grid_map.study_starts:
        raise ValueError(f"map {name!r}: gravity maps have no study starts")
    tasks = []
    for spec in grid_map.tasks:
        if set(spec.goal_cells) & set(colour_of_cell):
            raise ValueError(f"map {name!r}: the goal of task {spec.name!r} is coloured")
        reward = goal_reward(num_states, num_features, width, spec.goal_cells)
        # The study's starts leave out the few states from which no policy can ever reach the
        # goal (e.g. gravity east in the last column with no colour in it, for a goal at the
        # left): a person's demonstration from there could never end at the goal.
        reachable = can_reach(true_transitions, reward > 0, steps - 1)
        tasks.append(
            Task(
                name=spec.name,
                reward=reward,
                start=uniform(num_states, candidates),
                goal_cells=spec.goal_cells,
                study_start=uniform(num_states, (s for s in candidates if reachable[s])),
            )
        )

    layout = empty_layout(height, width, "floor")
    layout["colours"] = [
        {"row": row, "column": column, "colour": colour}
        for (row, column), colour in sorted(colour_of_cell.items())
    ]
    layout["gravity_of_colour"] = {colour: mapping[colour] for colour in groups}
    layout["drawing"] = drawing(["floor"], colours=groups, palette=palette)
    return make_environment(
        name=name,
        domain=DOMAIN,
        grid_map=grid_map,
        num_features=num_features,
        feature_names=GRAVITIES,
        horizon=steps,
        tasks=tasks,
        table=table,
        model=model,
        layout=layout,
        legend={
            "letters": {PLAIN: "floor", **colours},
            "palette": {} if palette is None else dict(palette),
        },
    )


def true_model_parameters(env: Environment) -> np.ndarray:
    """Logits under which the model's probabilities equal the true dynamics (within 1e-9):
    per colour, +30 on its true gravity and -30 on the others."""
    if env.domain != DOMAIN:
        raise ValueError(f"{env.name!r} is a {env.domain} environment, not {DOMAIN}")
    theta = np.empty(env.model.num_parameters)
    for i, parameter in enumerate(env.model.parameter_names):
        colour, gravity = parameter.split("->")
        theta[i] = TRUE_LOGIT if env.layout["gravity_of_colour"][colour] == gravity else -TRUE_LOGIT
    return theta
