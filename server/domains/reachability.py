"""Traps: the states from which a task's goal can never be reached under the true dynamics,
however the agent acts and however long it has.

    >>> from server import domains
    >>> from server.domains.reachability import trapped_states
    >>> traps = trapped_states(domains.make("flip"), 0)
    >>> len(traps.starts), traps.start_share   # gravity east in the last column, no colour
    (10, 0.025)
    >>> traps.named(domains.make("flip"), traps.starts)
    'gravity east at column 9, rows 0-9'

A state is trapped for a task when no sequence of actions reaches a goal state of the task
with positive probability: a backward search over the positive-probability transitions,
without a horizon. The starts are the states the task may start in, in the simulations
(``Task.start``) or in the user study (``Task.study_start``); the reachable states are those
some sequence of actions reaches from a start. A start that is trapped wastes its episode
whatever is taught; a reachable trapped state is one a demonstration or an agent's try may walk
into and never leave.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from server.domains.base import Environment
from server.domains.grid import can_reach, reachable_from

# How many trapped states a description names before "and N more".
NAMED = 6


@dataclass(frozen=True)
class Traps:
    """One task's traps. ``starts``: the trapped states among the task's starts (the states of
    positive probability in its simulation or study start distribution), ascending;
    ``start_states``: how many starts there are; ``start_share`` and ``study_start_share``: the
    probability the simulation's and the user study's start distributions put on trapped
    states; ``reachable``: the trapped states reachable from a start that are not starts;
    ``reachable_states``: how many states are reachable from the starts, starts included."""

    task: str
    starts: np.ndarray
    start_states: int
    start_share: float
    study_start_share: float
    reachable: np.ndarray
    reachable_states: int

    @staticmethod
    def named(env: Environment, states: np.ndarray, limit: int = NAMED) -> str:
        """The states in words, grouped by gravity or machine carried and by runs of cells
        along a row or a column, the first ``limit`` runs named, then 'and N more states'."""
        cells: dict[int, list[tuple[int, int]]] = {}  # feature -> its cells
        for state in states:
            cells.setdefault(env.feature_of(int(state)), []).append(env.cell_of(int(state)))
        parts: list[str] = []
        named = runs_named = 0
        for feature in sorted(cells):
            runs = min(_runs(cells[feature], 0), _runs(cells[feature], 1), key=len)
            runs = runs[: max(0, limit - runs_named)]
            if not runs:
                break
            runs_named += len(runs)
            named += sum(count for _, count in runs)
            words = "; ".join(text for text, _ in runs)
            parts.append(words if env.num_features == 1 else f"{_feature(env, feature)} at {words}")
        more = len(states) - named
        return "; ".join(parts) + (f"; and {more} more state{'s' * (more != 1)}" if more else "")


def _runs(cells: list[tuple[int, int]], axis: int) -> list[tuple[str, int]]:
    """Runs of adjacent cells along rows (``axis`` 0) or columns (1), each in words with its
    number of cells: 'row 6, columns 0-8', 'column 9, rows 0-9', 'row 1, column 4'."""
    runs: list[list[int]] = []  # [line, first, last]
    for cell in sorted(cells, key=lambda cell: (cell[axis], cell[1 - axis])):
        line, along = cell[axis], cell[1 - axis]
        if runs and runs[-1][0] == line and runs[-1][2] == along - 1:
            runs[-1][2] = along
        else:
            runs.append([line, along, along])
    names = ("row", "column") if axis == 0 else ("column", "row")
    words = []
    for line, first, last in runs:
        if first == last:
            row, column = (line, first) if axis == 0 else (first, line)
            words.append((f"row {row}, column {column}", 1))
        else:
            words.append((f"{names[0]} {line}, {names[1]}s {first}-{last}", last - first + 1))
    return words


def _feature(env: Environment, feature: int) -> str:
    """'gravity south', 'carrying the plow', 'carrying nothing'."""
    name = env.feature_names[feature]
    if env.domain == "gravity":
        return f"gravity {name}"
    return "carrying nothing" if name == "none" else f"carrying the {name}"


def describe(env: Environment, state: int) -> str:
    """A state in words: '(row 6, column 0, gravity south)', '(row 2, column 3, carrying the
    plow)', '(row 1, column 4)'."""
    row, column = env.cell_of(state)
    if env.num_features == 1:
        return f"(row {row}, column {column})"
    return f"(row {row}, column {column}, {_feature(env, env.feature_of(state))})"


def reaches_goal(env: Environment, task: int) -> np.ndarray:
    """Mask of the states from which the task's goal can be reached, in any number of steps."""
    goal = env.tasks[env.check_task(task)].reward > 0
    # Each step of the search adds at least one state until it stops: num_states steps suffice.
    return can_reach(env.true_transitions, goal, env.num_states)


def trapped_states(env: Environment, task: int) -> Traps:
    """The task's trapped starts and trapped reachable states (see the module docstring)."""
    chosen = env.tasks[env.check_task(task)]
    trapped = ~reaches_goal(env, task)
    study = chosen.study_start_distribution
    starts = (chosen.start > 0) | (study > 0)
    reachable = reachable_from(env.true_transitions, starts)
    return Traps(
        task=chosen.name,
        starts=np.flatnonzero(starts & trapped),
        start_states=int(starts.sum()),
        start_share=float(chosen.start[trapped].sum()),
        study_start_share=float(study[trapped].sum()),
        reachable=np.flatnonzero(reachable & trapped & ~starts),
        reachable_states=int(reachable.sum()),
    )
