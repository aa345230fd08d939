"""Farming: reach a field; each field terrain can only be entered with the right machine.
Soil needs the plow, immature crops (grass) the sprinkler, grown crops the harvester; dirt is
free. The learner does not know which machine works on which terrain: its model is, as the
paper authors' is, per machine a softmax over the four terrains, dirt included (dirt is never
the terrain a machine is tried on, so it only takes probability from the others: a machine's
chance on a field starts at 1/4), with no prior and the logits clipped to +-50.

States are (cell, machine carried) with machines none, plow, sprinkler, harvester. Machines
stand on dirt cells and stay there (they are sources): stepping onto a machine's cell moves
there and the carried machine becomes that one. Moving onto dirt always succeeds (known).
Moving onto a field cell of terrain t while carrying machine m succeeds with model probability
p = softmax(theta[m])[t] (row ``[moved, stay]`` = ``[p, 1 - p]``) and truly iff m works on t;
carrying nothing never enters a field (known). STAY and moves off the grid stay put; on dirt,
or carrying nothing, that is a known row. On a field cell while carrying a machine the row is,
as in the authors' model, ``[stay, stay]`` = ``[p, 1 - p]`` for that machine and the field's
terrain: the same certain outcome, which the authors' update counts as a success (their
gradient rule, ``TransitionModel.outcomes``; the exact gradient of such a row is 0).

Only the field cells carry a cost (``Environment.cost_cells``), as in the authors' learners.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from server.domains.base import NUM_ACTIONS, Environment, SoftmaxRowsModel, Task
from server.domains.drawing import drawing
from server.domains.grid import (
    GridMap,
    Successor,
    TransitionTable,
    empty_layout,
    goal_reward,
    known,
    make_environment,
    target_cell,
    uniform,
)

DOMAIN = "farming"
FEATURES: tuple[str, ...] = ("none", "plow", "sprinkler", "harvester")
MACHINES = FEATURES[1:]  # the model's softmax rows
TERRAINS: tuple[str, ...] = ("dirt", "soil", "grass", "crops")  # the model's softmax columns
PARAMETER_BOUND = 50.0  # the authors clip the logits here after every update
# Map letters.
DIRT = "."
TERRAIN_OF_LETTER: dict[str, str] = {".": "dirt", "s": "soil", "i": "grass", "c": "crops"}
MACHINE_OF_LETTER: dict[str, str] = {"P": "plow", "W": "sprinkler", "H": "harvester"}
# The true (hidden) rule: the terrain each machine works on.
TERRAIN_OF_MACHINE: dict[str, str] = {"plow": "soil", "sprinkler": "grass", "harvester": "crops"}
TRUE_LOGIT = 30.0  # softmax(+30 against -30) is within 1e-26 of one-hot
WIDTH = 2  # successors per (state, action)


@dataclass(frozen=True)
class Rules:
    """A farming variant's letters and rule: {letter: terrain} (dirt drawn '.'), {letter:
    machine} and {machine: the terrain it works on}. The defaults are the paper's; the order of
    the terrains and machines is the order of the model's softmax columns and rows."""

    terrain_of_letter: dict[str, str] = field(default_factory=lambda: dict(TERRAIN_OF_LETTER))
    machine_of_letter: dict[str, str] = field(default_factory=lambda: dict(MACHINE_OF_LETTER))
    terrain_of_machine: dict[str, str] = field(default_factory=lambda: dict(TERRAIN_OF_MACHINE))
    palette: dict[str, str] = field(default_factory=dict)  # {name: "#rrggbb"} the page lacks

    @property
    def terrains(self) -> tuple[str, ...]:
        return ("dirt", *(t for t in self.terrain_of_letter.values() if t != "dirt"))

    @property
    def machines(self) -> tuple[str, ...]:
        return tuple(self.machine_of_letter.values())

    @property
    def features(self) -> tuple[str, ...]:
        return ("none", *self.machines)


def horizon(height: int, width: int) -> int:
    return 4 * (width + height)


def build(
    name: str, grid_map: GridMap, horizon_steps: int | None = None, rules: Rules | None = None
) -> Environment:
    """The environment of a farming map. ``horizon_steps``: the horizon, unless the domain's
    own, 4 * (width + height); ``rules``: the variant's letters and rule (the paper's unless
    given).

    One function, as the other domains' ``build``: the map's cells, the rule's transitions,
    the model, the tasks and the layout, in the order the environment is made of them, each
    reading the names the step before defined."""
    rules = Rules() if rules is None else rules
    features, machines, terrains = rules.features, rules.machines, rules.terrains
    grid_map.check_characters("".join(rules.terrain_of_letter) + "".join(rules.machine_of_letter))
    if grid_map.goal_letters:
        raise ValueError(f"map {name!r}: farming tasks are fields, not letters")
    height, width = grid_map.height, grid_map.width
    num_features = len(features)
    num_states = height * width * num_features
    # Machines stand on dirt.
    terrain = {
        cell: rules.terrain_of_letter.get(grid_map.char(cell), "dirt") for cell in grid_map.cells()
    }
    machine_of_cell = {
        cell: rules.machine_of_letter[grid_map.char(cell)]
        for cell in grid_map.cells()
        if grid_map.char(cell) in rules.machine_of_letter
    }

    def state_of(cell: tuple[int, int], feature: int) -> int:
        return (cell[0] * width + cell[1]) * num_features + feature

    def parametric(carried: str, target_terrain: str) -> tuple[int, float]:
        """The model parameter of ``carried`` on ``target_terrain``, and whether it truly works."""
        index = machines.index(carried) * len(terrains) + terrains.index(target_terrain)
        return index, float(rules.terrain_of_machine[carried] == target_terrain)

    table = TransitionTable(num_states, WIDTH)
    for cell in grid_map.cells():
        for feature, carried in enumerate(features):
            state = state_of(cell, feature)
            for action in range(NUM_ACTIONS):
                target = target_cell(cell, action, height, width)
                if target is None:
                    if carried == "none" or terrain[cell] == "dirt":
                        table.set(state, action, known(state))
                    else:
                        index, works = parametric(carried, terrain[cell])
                        table.set(
                            state,
                            action,
                            [
                                Successor(state, 0.0, 1.0, index, works, outcome=1),
                                Successor(state, 1.0, -1.0, index, 1.0 - works, outcome=1),
                            ],
                        )
                elif terrain[target] == "dirt":
                    machine = machine_of_cell.get(target)
                    new = feature if machine is None else features.index(machine)
                    table.set(state, action, known(state_of(target, new)))
                elif carried == "none":
                    table.set(state, action, known(state))
                else:
                    index, works = parametric(carried, terrain[target])
                    table.set(
                        state,
                        action,
                        [
                            Successor(state_of(target, feature), 0.0, 1.0, index, works, 1),
                            Successor(state, 1.0, -1.0, index, 1.0 - works, -1),
                        ],
                    )
    model = SoftmaxRowsModel(
        **table.model_arrays(),
        num_parameters=len(machines) * len(terrains),
        initial_value=0.0,
        parameter_names=[f"{machine}->{t}" for machine in machines for t in terrains],
        groups=len(machines),
        choices=len(terrains),
        prior_sd=None,
        parameter_bound=PARAMETER_BOUND,
        outcomes=table.outcomes,
    )
    cost_cells = np.array([terrain[cell] != "dirt" for cell in grid_map.cells()])

    start = uniform(
        num_states,
        (
            state_of(cell, 0)
            for cell in grid_map.cells()
            if terrain[cell] == "dirt" and cell not in machine_of_cell and cell in grid_map.start
        ),
    )
    if grid_map.study_starts:
        raise ValueError(f"map {name!r}: farming maps have no study starts")
    tasks = []
    for spec in grid_map.tasks:
        kinds = {terrain[cell] for cell in spec.goal_cells}
        if len(kinds) != 1 or kinds == {"dirt"}:
            raise ValueError(f"map {name!r}: task {spec.name!r} must cover one field terrain")
        tasks.append(
            Task(
                name=spec.name,
                reward=goal_reward(num_states, num_features, width, spec.goal_cells),
                start=start,
                goal_cells=spec.goal_cells,
            )
        )

    layout = empty_layout(height, width, "dirt")
    layout["terrain"] = [
        [terrain[(row, column)] for column in range(width)] for row in range(height)
    ]
    layout["machines"] = [
        {"row": row, "column": column, "machine": machine}
        for (row, column), machine in sorted(machine_of_cell.items())
    ]
    layout["drawing"] = drawing(
        terrains,
        {machine: rules.terrain_of_machine[machine] for machine in machines},
        palette=rules.palette,
    )
    return make_environment(
        name=name,
        domain=DOMAIN,
        grid_map=grid_map,
        num_features=num_features,
        feature_names=features,
        horizon=horizon_steps or horizon(height, width),
        tasks=tasks,
        table=table,
        model=model,
        layout=layout,
        cost_cells=cost_cells,
        legend={
            "letters": {**rules.terrain_of_letter, **rules.machine_of_letter},
            "palette": dict(rules.palette),
            "works_on": dict(rules.terrain_of_machine),
        },
    )


def true_model_parameters(env: Environment) -> np.ndarray:
    """Logits under which the model's probabilities equal the true dynamics (within 1e-9):
    per machine, +30 on the terrain it works on and -30 on the others."""
    if env.domain != DOMAIN:
        raise ValueError(f"{env.name!r} is a {env.domain} environment, not {DOMAIN}")
    works_on = env.legend.get("works_on", TERRAIN_OF_MACHINE)
    return np.asarray(
        [
            TRUE_LOGIT if works_on[machine] == terrain else -TRUE_LOGIT
            for machine, terrain in (name.split("->") for name in env.model.parameter_names)
        ]
    )
