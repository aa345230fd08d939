"""Navigation: walk to a goal cell; walls block moves. The learner does not know where the
walls are: its model has one parameter per cell, and a move into cell t fails (the agent
stays) with probability sigmoid(theta_t).

States are cells (``num_features = 1``). For a move from cell c into an on-grid cell t != c the
model row is ``[state(t), state(c)]`` with probabilities ``[1 - p_t, p_t]``; STAY and moves off
the grid stay put, known to the learner. Walls are cells like any other (unreachable, but their
rows are defined by the same rule).
"""

from __future__ import annotations

import numpy as np

from server.domains.base import NUM_ACTIONS, Environment, SigmoidModel, Task
from server.domains.drawing import drawing
from server.domains.grid import (
    GridMap,
    Region,
    Successor,
    TransitionTable,
    empty_layout,
    goal_reward,
    known,
    make_environment,
    target_cell,
    uniform,
)

DOMAIN = "navigation"
WALL, FLOOR = "#", "."
INITIAL_LOGIT = -3.0  # cells presumed free (reference initialisation)
TRUE_LOGIT = 30.0  # sigmoid(+-30) is within 1e-13 of 1 or 0
WIDTH = 2  # successors per (state, action)


def horizon(height: int, width: int) -> int:
    return 2 * (width + height)


def build(name: str, grid_map: GridMap, horizon_steps: int | None = None) -> Environment:
    """The environment of a navigation map (``horizon_steps``: the horizon, unless the
    domain's own, 2 * (width + height))."""
    grid_map.check_characters(WALL + FLOOR)
    height, width = grid_map.height, grid_map.width
    walls = [cell for cell in grid_map.cells() if grid_map.char(cell) == WALL]
    wall_set = set(walls)
    num_cells = height * width

    table = TransitionTable(num_cells, WIDTH)
    for cell in grid_map.cells():
        state = cell[0] * width + cell[1]
        for action in range(NUM_ACTIONS):
            target = target_cell(cell, action, height, width)
            if target is None:
                table.set(state, action, known(state))
                continue
            t = target[0] * width + target[1]
            blocked = float(target in wall_set)
            table.set(
                state,
                action,
                [
                    Successor(t, 1.0, -1.0, t, 1.0 - blocked),  # 1 - p_t: the move succeeds
                    Successor(state, 0.0, 1.0, t, blocked),  # p_t: the move into t fails
                ],
            )
    model = SigmoidModel(
        **table.model_arrays(),
        num_parameters=num_cells,
        initial_value=INITIAL_LOGIT,
        parameter_names=[f"fail({r},{c})" for r, c in grid_map.cells()],
    )

    free = [cell for cell in grid_map.cells() if cell not in wall_set]

    def starts(region: Region) -> np.ndarray:
        return uniform(num_cells, (r * width + c for r, c in free if (r, c) in region))

    tasks = []
    for spec in grid_map.tasks:
        if wall_set & set(spec.goal_cells):
            raise ValueError(f"map {name!r}: the goal of task {spec.name!r} is a wall")
        study = grid_map.study_starts.get(spec.name)
        tasks.append(
            Task(
                name=spec.name,
                reward=goal_reward(num_cells, 1, width, spec.goal_cells),
                # The authors' simulations start a task with study starts in them too.
                start=starts(grid_map.start if study is None else study),
                goal_cells=spec.goal_cells,
                study_start=None if study is None else starts(study),
            )
        )

    layout = empty_layout(height, width, "floor")
    layout["walls"] = [[r, c] for r, c in walls]
    layout["drawing"] = drawing(["floor", "wall"])
    return make_environment(
        name=name,
        domain=DOMAIN,
        grid_map=grid_map,
        num_features=1,
        feature_names=("none",),
        horizon=horizon_steps or horizon(height, width),
        tasks=tasks,
        table=table,
        model=model,
        layout=layout,
        legend={"letters": {WALL: "wall", FLOOR: "floor"}, "palette": {}},
    )


def true_model_parameters(env: Environment) -> np.ndarray:
    """Logits under which the model's probabilities equal the true dynamics (within 1e-9):
    +30 on walls (moves into them fail), -30 elsewhere."""
    if env.domain != DOMAIN:
        raise ValueError(f"{env.name!r} is a {env.domain} environment, not {DOMAIN}")
    theta = np.full(env.num_cells, -TRUE_LOGIT)
    for row, column in env.layout["walls"]:
        theta[row * env.width + column] = TRUE_LOGIT
    return theta
