"""Reading the text maps in ``maps/`` and the helpers every domain shares to turn a map into an
:class:`~server.domains.base.Environment`.

A map file is a small header followed by the grid, drawn exactly as in the reference (column
digits on top, row numbers on the left, one character per cell)::

    # a comment
    task: A                                    goal = the cells drawn as the letter A
    task: Top = T                              task "Top", goal = the cells drawn as T
    task: Soil field = rows 1-2, columns 1-2   goal = every cell of that rectangle
    start: rows 8-10                           where tasks start (default: anywhere)
    study-start A: columns 0-2                 where task A starts in the user study
    gravity of orange: south                   the true (hidden) effect of a colour
        01234567890
      0 ...........
      1 .B.......A.

Regions are ``anywhere``, ``rows a-b``, ``columns a-b`` or ``rows a-b, columns c-d`` (inclusive;
``rows 4`` is a single row). Which cells of a start region a task can start on, and what the
other characters mean, is the domain's business (``navigation.py``, ``gravity.py``,
``farming.py``). Tasks keep the order of their ``task:`` lines.

The ``layout`` dictionary every environment carries (merged into ``Environment.describe()``
for the browser page; plain lists, ints and strings only) has these keys in every domain:

- ``walls``: ``[[row, column], ...]``, the wall cells (navigation only; otherwise empty);
- ``terrain``: one list per row of one string per cell: ``"floor"`` for navigation and gravity
  cells (walls included; they are drawn from ``walls``), and ``"dirt"``, ``"soil"``,
  ``"grass"`` (immature crops) or ``"crops"`` (grown crops) for farming; the decoy fields are
  terrain like any other;
- ``machines``: ``[{"row", "column", "machine"}, ...]`` with ``machine`` one of ``"plow"``,
  ``"sprinkler"``, ``"harvester"`` (farming only);
- ``colours``: ``[{"row", "column", "colour"}, ...]`` with ``colour`` one of ``"orange"``,
  ``"green"``, ``"purple"`` (gravity only);
- ``gravity_of_colour``: ``{colour: direction}``, the true hidden mapping of each colour
  present to ``"north"``, ``"south"``, ``"east"`` or ``"west"`` (gravity only; the server
  decides whether to show it);
- ``drawing``: ``{"terrains", "machines", "colours"}``, each kind of the environment (its
  terrains, its machines, its gravity colours) with its name for people and its colour
  (``drawing.py``): the page draws a study's own kinds from it.

The map format is read in this one module (the header, the regions, the grid and the table
builder every domain uses), as a map file is written: one format, one reader.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from importlib import resources
from typing import Any, TypedDict

import numpy as np

from server.domains.base import (
    DELTAS,
    NUM_ACTIONS,
    Environment,
    SparseTransitions,
    Task,
    TransitionModel,
)

Cell = tuple[int, int]

_RANGE = re.compile(r"^(rows?|columns?)\s+(\d+)(?:\s*-\s*(\d+))?$")
_GRID_ROW = re.compile(r"^\s*(\d+) (\S+)$")
_COLUMN_HEADER = re.compile(r"^\s+(\d+)$")
_KEY_VALUE = re.compile(r"^([A-Za-z][A-Za-z -]*?)\s*:\s*(.+)$")


@dataclass(frozen=True)
class Region:
    """A rectangle of rows and columns; ``None`` means every row (column)."""

    rows: range | None = None
    columns: range | None = None

    def __contains__(self, cell: object) -> bool:
        if not isinstance(cell, tuple) or len(cell) != 2:
            return False
        row, column = cell
        return (self.rows is None or row in self.rows) and (
            self.columns is None or column in self.columns
        )

    @classmethod
    def parse(cls, text: str) -> Region:
        text = text.strip()
        if text == "anywhere":
            return cls()
        spans: dict[str, range] = {}
        for part in text.split(","):
            match = _RANGE.match(part.strip())
            if match is None:
                raise ValueError(f"cannot read region {text!r}: expected 'rows a-b, columns c-d'")
            axis = "rows" if match.group(1).startswith("row") else "columns"
            if axis in spans:
                raise ValueError(f"region {text!r} gives {axis} twice")
            first = int(match.group(2))
            last = int(match.group(3)) if match.group(3) is not None else first
            if last < first:
                raise ValueError(f"region {text!r} has an empty range")
            spans[axis] = range(first, last + 1)
        return cls(spans.get("rows"), spans.get("columns"))


@dataclass(frozen=True)
class TaskSpec:
    """A task as the map states it: its name and its goal cells."""

    name: str
    goal_cells: tuple[Cell, ...]


@dataclass(frozen=True, order=True)
class Problem:
    """One problem of a map, at its line and column of the map's text (both from 1)."""

    line: int
    column: int
    message: str

    def __str__(self) -> str:
        if self.line == 0:  # not in the map's text: a key of the environment's definition
            return self.message
        return f"line {self.line}, column {self.column}: {self.message}"


class MapProblems(ValueError):
    """A map with problems; ``problems`` holds every one, in the order of the text."""

    def __init__(self, name: str, problems: Sequence[Problem]) -> None:
        self.name = name
        self.problems = tuple(sorted(problems))
        count = len(self.problems)
        listed = "\n".join(f"  {problem}" for problem in self.problems)
        super().__init__(f"map {name!r} has {count} problem{'s' * (count != 1)}:\n{listed}")


@dataclass(frozen=True)
class GridMap:
    """One parsed map file: the grid (one string per row) and its header."""

    name: str
    grid: tuple[str, ...]
    tasks: tuple[TaskSpec, ...]
    goal_letters: frozenset[str]
    start: Region = field(default_factory=Region)
    study_starts: dict[str, Region] = field(default_factory=dict)
    gravity_of_colour: dict[str, str] = field(default_factory=dict)
    # Where things are in the text, for problems: each grid row's line and the text column of
    # its first cell, and (line, column) of header entries ("task NAME", "start",
    # "gravity of COLOUR").
    row_lines: tuple[int, ...] = ()
    row_columns: tuple[int, ...] = ()
    places: dict[str, tuple[int, int]] = field(default_factory=dict)

    @property
    def height(self) -> int:
        return len(self.grid)

    @property
    def width(self) -> int:
        return len(self.grid[0])

    def cells(self) -> Iterable[Cell]:
        for row in range(self.height):
            for column in range(self.width):
                yield row, column

    def char(self, cell: Cell) -> str:
        return self.grid[cell[0]][cell[1]]

    def where(self, cell: Cell) -> tuple[int, int]:
        """The (line, column) of a cell in the map's text."""
        if not self.row_lines:
            return cell[0] + 1, cell[1] + 1
        return self.row_lines[cell[0]], self.row_columns[cell[0]] + cell[1]

    def place(self, key: str) -> tuple[int, int]:
        """The (line, column) of a header entry (the grid's first line when it has none)."""
        return self.places.get(key, (self.row_lines[0] if self.row_lines else 1, 1))

    def check_characters(self, allowed: str) -> None:
        """Reject a map drawing a character its domain does not know (goal letters aside)."""
        for cell in self.cells():
            char = self.char(cell)
            if char not in allowed and char not in self.goal_letters:
                raise ValueError(f"map {self.name!r}: unknown character {char!r} at {cell}")


def load_map(name: str) -> GridMap:
    """Read ``maps/<name>.txt`` shipped with the package."""
    path = resources.files("server.domains").joinpath("maps").joinpath(f"{name}.txt")
    return parse_map(name, path.read_text(encoding="utf-8"))


def parse_map(name: str, text: str) -> GridMap:
    """Read a map, failing at its first problem (``read_map`` gives every one)."""
    grid_map, problems = read_map(name, text)
    if problems or grid_map is None:
        first = min(problems)
        raise ValueError(f"map {name!r} line {first.line}: {first.message}")
    return grid_map


@dataclass(frozen=True)
class _Entry:
    key: str
    value: str
    line: int
    column: int


def read_map(name: str, text: str) -> tuple[GridMap | None, list[Problem]]:
    """Read a map and list every problem of its text (the map is None when the grid itself
    cannot be read)."""
    problems: list[Problem] = []
    header: list[_Entry] = []
    grid: list[str] = []
    row_lines: list[int] = []
    row_columns: list[int] = []
    column_header: str | None = None
    header_place = (1, 1)
    for number, line in enumerate(text.splitlines(), start=1):
        if not line.strip() or (line.startswith("#") and column_header is None):
            continue
        if column_header is None:
            header_match = _COLUMN_HEADER.match(line)
            if header_match is not None:
                column_header = header_match.group(1)
                header_place = (number, header_match.start(1) + 1)
                continue
            key_value = _KEY_VALUE.match(line)
            if key_value is None:
                problems.append(Problem(number, 1, f"expected 'key: value', got {line!r}"))
                continue
            header.append(
                _Entry(
                    key_value.group(1), key_value.group(2).strip(), number, key_value.start(2) + 1
                )
            )
            continue
        row_match = _GRID_ROW.match(line)
        if row_match is None or int(row_match.group(1)) != len(grid):
            problems.append(
                Problem(number, 1, f"expected row {len(grid)} of the grid, got {line!r}")
            )
            if row_match is None:
                continue
        assert row_match is not None
        grid.append(row_match.group(2))
        row_lines.append(number)
        row_columns.append(row_match.start(2) + 1)
    if column_header is None or not grid:
        problems.append(Problem(1, 1, "the map has no grid (a line of column digits, then rows)"))
        return None, problems
    width = len(column_header)
    if column_header != "".join(str(column % 10) for column in range(width)):
        problems.append(Problem(*header_place, f"column header {column_header!r} is not 0123..."))
    for row, (cells, row_line) in enumerate(zip(grid, row_lines, strict=True)):
        if len(cells) != width:
            problems.append(
                Problem(
                    row_line,
                    row_columns[row] + min(len(cells), width),
                    f"row {row} is {len(cells)} cells wide: every row must be {width} cells wide",
                )
            )
    if any(len(cells) != width for cells in grid):
        # The header's own problems still count: read it against the rows cut or padded.
        _read_header(name, tuple(cells[:width].ljust(width) for cells in grid), header, problems)
        return None, problems
    grid_map = _read_header(name, tuple(grid), header, problems)
    located = replace(grid_map, row_lines=tuple(row_lines), row_columns=tuple(row_columns))
    return located, problems


def _region(entry: _Entry, text: str, height: int, width: int, problems: list[Problem]) -> Region:
    """A region of the header, its problems listed (an unreadable one reads as no cell)."""
    try:
        region = Region.parse(text)
    except ValueError as error:
        problems.append(Problem(entry.line, entry.column, str(error)))
        return Region(range(0), range(0))
    for axis, span, size in (("rows", region.rows, height), ("columns", region.columns, width)):
        if span is not None and span.stop > size:
            problems.append(
                Problem(
                    entry.line,
                    entry.column,
                    f"region {text!r} goes past the grid's last {axis[:-1]} ({size - 1})",
                )
            )
    return region


def _read_header(
    name: str, grid: tuple[str, ...], header: list[_Entry], problems: list[Problem]
) -> GridMap:
    height, width = len(grid), len(grid[0])
    tasks: list[TaskSpec] = []
    goal_letters: set[str] = set()
    start = Region()
    study_starts: dict[str, Region] = {}
    gravity_of_colour: dict[str, str] = {}
    places: dict[str, tuple[int, int]] = {}
    for entry in header:
        key, value = entry.key, entry.value
        if key == "task":
            task_name, _, goal = (part.strip() for part in value.partition("="))
            goal = goal or task_name
            if len(goal) == 1:
                cells = tuple(
                    (r, c) for r in range(height) for c in range(width) if grid[r][c] == goal
                )
                goal_letters.add(goal)
            else:
                region = _region(entry, goal, height, width, problems)
                cells = tuple(
                    (r, c) for r in range(height) for c in range(width) if (r, c) in region
                )
            if f"task {task_name}" in places:
                problems.append(
                    Problem(
                        entry.line,
                        entry.column,
                        f"tasks must have distinct names: {task_name!r} is given twice",
                    )
                )
                continue
            places[f"task {task_name}"] = (entry.line, entry.column)
            if not cells:
                problems.append(
                    Problem(entry.line, entry.column, f"task {task_name!r} has no goal cell")
                )
                continue
            tasks.append(TaskSpec(task_name, cells))
        elif key == "start":
            places["start"] = (entry.line, entry.column)
            start = _region(entry, value, height, width, problems)
        elif key.startswith("study-start "):
            task_name = key.removeprefix("study-start ").strip()
            places[f"study-start {task_name}"] = (entry.line, entry.column)
            study_starts[task_name] = _region(entry, value, height, width, problems)
        elif key.startswith("gravity of "):
            colour = key.removeprefix("gravity of ").strip()
            places[f"gravity of {colour}"] = (entry.line, entry.column)
            gravity_of_colour[colour] = value
        else:
            problems.append(Problem(entry.line, 1, f"unknown header key {key!r}"))
    if not any(key.startswith("task ") for key in places):
        problems.append(Problem(1, 1, "the map has no task: add a line 'task: A'"))
    named = {key.removeprefix("task ") for key in places if key.startswith("task ")}
    for task_name in sorted(set(study_starts) - named):
        problems.append(
            Problem(
                *places[f"study-start {task_name}"],
                f"study-start for unknown tasks [{task_name!r}]",
            )
        )
    return GridMap(
        name,
        grid,
        tuple(tasks),
        frozenset(goal_letters),
        start,
        study_starts,
        gravity_of_colour,
        places=places,
    )


# -- building environments ------------------------------------------------------------------


def target_cell(cell: Cell, action: int, height: int, width: int) -> Cell | None:
    """The cell an action moves towards, or ``None`` for STAY and moves off the grid."""
    row, column = cell[0] + DELTAS[action][0], cell[1] + DELTAS[action][1]
    if (row, column) == cell or not (0 <= row < height and 0 <= column < width):
        return None
    return row, column


@dataclass(frozen=True)
class Successor:
    """One entry of a transition row: T_theta(s, a, state) = const + coef * p(theta)[index],
    and the true probability (0 or 1) of reaching ``state``."""

    state: int
    const: float
    coef: float
    index: int
    true: float
    # The authors' farming update: +1 a success, -1 a failure (see TransitionModel.outcomes).
    outcome: int = 0


def known(state: int) -> list[Successor]:
    """A deterministic outcome the learner knows (STAY, a move off the grid, a forbidden move,
    a move onto dirt...)."""
    return [Successor(state, 1.0, 0.0, 0, 1.0)]


class ModelArrays(TypedDict):
    """The arrays a TransitionModel is built from (see server.domains.base)."""

    next_states: np.ndarray
    const: np.ndarray
    coef: np.ndarray
    index: np.ndarray


@dataclass
class TransitionTable:
    """Sparse model arrays and true transitions filled row by row, padded to ``width``
    successors with zero-probability entries pointing back at the state itself."""

    num_states: int
    width: int
    num_actions: int = NUM_ACTIONS

    def __post_init__(self) -> None:
        shape = (self.num_states, self.num_actions, self.width)
        self.next_states = np.broadcast_to(
            np.arange(self.num_states, dtype=np.int64)[:, None, None], shape
        ).copy()
        self.const = np.zeros(shape)
        self.coef = np.zeros(shape)
        self.index = np.zeros(shape, dtype=np.int64)
        self.true = np.zeros(shape)
        self.outcomes = np.zeros(shape, dtype=np.int64)
        self._filled = np.zeros(shape[:2], dtype=bool)

    def set(self, state: int, action: int, successors: Sequence[Successor]) -> None:
        if len(successors) > self.width:
            raise ValueError(f"{len(successors)} successors exceed the width {self.width}")
        if sum(successor.true for successor in successors) != 1.0:
            raise ValueError(f"true probabilities of ({state}, {action}) do not sum to 1")
        for m, successor in enumerate(successors):
            self.next_states[state, action, m] = successor.state
            self.const[state, action, m] = successor.const
            self.coef[state, action, m] = successor.coef
            self.index[state, action, m] = successor.index
            self.true[state, action, m] = successor.true
            self.outcomes[state, action, m] = successor.outcome
        self._filled[state, action] = True

    def true_transitions(self) -> SparseTransitions:
        """The true dynamics on the same successor lists as the model (one entry 1, the rest 0)."""
        if not self._filled.all():
            raise ValueError("every (state, action) row must be set")
        return SparseTransitions(self.next_states, self.true)

    def model_arrays(self) -> ModelArrays:
        if not self._filled.all():
            raise ValueError("every (state, action) row must be set")
        return {
            "next_states": self.next_states,
            "const": self.const,
            "coef": self.coef,
            "index": self.index,
        }


def uniform(num_states: int, states: Iterable[int]) -> np.ndarray:
    """The uniform distribution over ``states``."""
    chosen = sorted(set(states))
    if not chosen:
        raise ValueError("a start distribution needs at least one state")
    distribution = np.zeros(num_states)
    distribution[chosen] = 1.0 / len(chosen)
    return distribution


def empty_layout(height: int, width: int, terrain: str) -> dict[str, Any]:
    """The layout keys every environment has (see the module docstring)."""
    return {
        "walls": [],
        "terrain": [[terrain] * width for _ in range(height)],
        "machines": [],
        "colours": [],
        "gravity_of_colour": {},
    }


def can_reach(true_transitions: SparseTransitions, goal: np.ndarray, max_steps: int) -> np.ndarray:
    """Mask of the states from which some sequence of at most ``max_steps`` actions reaches a
    goal state under the (deterministic) true dynamics."""
    reached = goal.copy()
    possible = true_transitions.probabilities > 0
    for _ in range(max_steps):
        successors_reached = (reached[true_transitions.next_states] & possible).any(axis=2)
        updated = reached | successors_reached.any(axis=1)
        if np.array_equal(updated, reached):
            break
        reached = updated
    return reached


def reachable_from(true_transitions: SparseTransitions, starts: np.ndarray) -> np.ndarray:
    """Mask of the states some sequence of actions reaches from a state of ``starts`` (a mask;
    included) under the true dynamics."""
    reached = starts.copy()
    frontier = np.flatnonzero(starts)
    possible = true_transitions.probabilities > 0
    while frontier.size:
        successors = np.unique(true_transitions.next_states[frontier][possible[frontier]])
        frontier = successors[~reached[successors]]
        reached[frontier] = True
    return reached


def make_environment(
    *,
    name: str,
    domain: str,
    grid_map: GridMap,
    num_features: int,
    feature_names: tuple[str, ...],
    horizon: int,
    tasks: Sequence[Task],
    table: TransitionTable,
    model: TransitionModel,
    layout: dict[str, Any],
    cost_cells: np.ndarray | None = None,
    legend: dict[str, Any] | None = None,
) -> Environment:
    """Assemble an environment and make its arrays read-only: ``make`` shares one instance."""
    environment = Environment(
        name=name,
        domain=domain,
        height=grid_map.height,
        width=grid_map.width,
        num_features=num_features,
        horizon=horizon,
        tasks=tuple(tasks),
        true_transitions=table.true_transitions(),
        model=model,
        layout=layout,
        feature_names=feature_names,
        cost_cells=np.zeros(0, dtype=bool) if cost_cells is None else cost_cells,
        legend={} if legend is None else legend,
    )
    arrays: list[np.ndarray] = [
        environment.true_transitions.next_states,
        environment.true_transitions.probabilities,
        environment.state_cells,
        environment.cost_cells,
        model.next_states,
        model.const,
        model.coef,
        model.index,
    ]
    for task in environment.tasks:
        arrays += [task.reward, task.start]
        if task.study_start is not None:
            arrays.append(task.study_start)
    for array in arrays:
        array.flags.writeable = False
    return environment


def goal_reward(
    num_states: int, num_features: int, width: int, cells: Iterable[Cell]
) -> np.ndarray:
    """Reward 1 on every state (any feature) of the goal cells, 0 elsewhere."""
    reward = np.zeros(num_states)
    for row, column in cells:
        cell = row * width + column
        reward[cell * num_features : (cell + 1) * num_features] = 1.0
    return reward
