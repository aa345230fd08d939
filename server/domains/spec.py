"""Environments defined by a study rather than shipped: a specification (name, domain, map text
and the domain's options) that is checked for every problem at once, then built exactly as the
built-in environments are.

    >>> from server.domains.spec import EnvironmentSpec
    >>> spec = EnvironmentSpec(name="corridor", domain="navigation", map=CORRIDOR)  # doctest: +SKIP
    >>> spec.problems()  # every problem, each with its line and column in the map   # doctest: +SKIP
    []

The map is text in the format of ``maps/`` (``grid.py``). Beyond the built-in maps' header, a
specification may give its horizon (else the domain's own), the colours drawn for names the
page's palette lacks, and its domain's rule: in gravity, more colours (a lower-case letter and
a name) and each colour's gravity; in farming, more terrains (a lower-case letter), more
machines (a capital letter) and the terrain each machine works on.

The checks (``problems``): a letter the domain does not know; a goal that is a wall, a colour,
dirt or a mix of fields; a task whose goal no start can reach within the horizon; a start
region with no start cell, or with start cells cut off from a goal; trapped starts (states of a
task's start distribution from which its goal can never be reached) above the share the
specification accepts (none unless it says); a machine no start can ever reach; more states
than ``max_states``; and whatever the map's text itself gets wrong.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from server.domains import farming, gravity, navigation
from server.domains.base import Environment
from server.domains.grid import GridMap, MapProblems, Problem, can_reach, reachable_from, read_map
from server.domains.reachability import trapped_states

DOMAIN_NAMES: tuple[str, ...] = ("navigation", "gravity", "farming")
# The most states a study's environment may have unless the study says otherwise: about the
# size at which one BAM update takes a few seconds on a 2-core AMD EPYC (``bam-study check``
# prints the estimate per learner).
DEFAULT_MAX_STATES = 4000
NAME = re.compile(r"^[a-z][a-z0-9-]{0,39}$")
THING_NAME = re.compile(r"^[a-z][a-z ]{0,29}$")
HEX = re.compile(r"^#[0-9A-Fa-f]{6}$")
DIRECTIONS = gravity.GRAVITIES


@dataclass(frozen=True)
class EnvironmentSpec:
    """An environment as a study file defines it (see the module docstring).

    ``colours``: {name: "#rrggbb"}, the colour drawn for a terrain, machine or gravity colour;
    ``gravity_colours``: {lower-case letter: colour} added to orange (o), green (g) and
    purple (p); ``gravity``: {colour: north, south, east or west} (a map's ``gravity of``
    lines give it too); ``terrains``: {lower-case letter: terrain} added to soil (s), grass (i)
    and crops (c); ``machines``: {capital letter: machine} added to the plow (P), sprinkler (W)
    and harvester (H); ``works_on``: {machine: terrain}, the terrain each machine enters
    (required for a new machine; the paper's machines keep theirs unless given);
    ``max_trapped_start_share``: the share of a task's start probability (in the simulations
    or in the user study) that may lie on trapped starts, states from which its goal can never
    be reached (``reachability.py``); above it the map is refused."""

    name: str
    domain: str
    map: str
    horizon: int | None = None
    colours: dict[str, str] = field(default_factory=dict)
    gravity_colours: dict[str, str] = field(default_factory=dict)
    gravity: dict[str, str] = field(default_factory=dict)
    terrains: dict[str, str] = field(default_factory=dict)
    machines: dict[str, str] = field(default_factory=dict)
    works_on: dict[str, str] = field(default_factory=dict)
    max_trapped_start_share: float = 0.0

    # -- the checks -----------------------------------------------------------------------
    def problems(self, max_states: int = DEFAULT_MAX_STATES) -> list[Problem]:
        """Every problem of this environment, in the order of the map's text (line 0: the
        specification's own keys)."""
        return _check(self, max_states)[1]

    def build(self, max_states: int = DEFAULT_MAX_STATES) -> Environment:
        """The environment, or ``MapProblems`` listing every problem."""
        environment, problems = _check(self, max_states)
        if problems or environment is None:
            raise MapProblems(self.name, problems)
        return environment

    # -- the domain's options -------------------------------------------------------------
    def _options(self, problems: list[Problem]) -> dict[str, Any]:
        """The domain's keyword arguments to ``build``; problems of the keys listed."""
        say = _spec_problem(problems)
        used = {navigation.WALL, navigation.FLOOR}
        for name, hex_colour in self.colours.items():
            if not HEX.match(hex_colour):
                say(f"colours.{name}: {hex_colour!r} is not a colour #rrggbb")
        if self.domain == "gravity":
            for key in ("terrains", "machines", "works_on"):
                if getattr(self, key):
                    say(f"{key}: a gravity environment has no {key.replace('_', ' ')}")
            colours = dict(gravity.COLOURS)
            for letter, colour in self.gravity_colours.items():
                _check_thing(say, "gravity_colours", letter, colour, str.islower, used, colours)
                colours[letter] = colour
            return {"colours": colours, "palette": dict(self.colours)}
        if self.domain == "farming":
            for key in ("gravity_colours", "gravity"):
                if getattr(self, key):
                    say(f"{key}: a farming environment has no {key.replace('_', ' ')}")
            terrains = dict(farming.TERRAIN_OF_LETTER)
            machines = dict(farming.MACHINE_OF_LETTER)
            for letter, terrain in self.terrains.items():
                _check_thing(say, "terrains", letter, terrain, str.islower, used, terrains)
                terrains[letter] = terrain
            for letter, machine in self.machines.items():
                _check_thing(say, "machines", letter, machine, str.isupper, used, machines)
                machines[letter] = machine
            works_on = {
                machine: terrain
                for machine, terrain in farming.TERRAIN_OF_MACHINE.items()
                if machine in machines.values()
            }
            for machine, terrain in self.works_on.items():
                if machine not in machines.values():
                    say(f"works_on.{machine}: no machine is called {machine!r}")
                elif terrain not in terrains.values() or terrain == "dirt":
                    say(f"works_on.{machine}: {terrain!r} is not a field terrain of the map")
                else:
                    works_on[machine] = terrain
            for machine in machines.values():
                if machine not in works_on:
                    say(f"works_on: say which terrain the {machine} works on")
            rules = farming.Rules(terrains, machines, works_on, dict(self.colours))
            return {"rules": rules}
        for key in ("gravity_colours", "gravity", "terrains", "machines", "works_on"):
            if getattr(self, key):
                say(f"{key}: a navigation environment has no {key.replace('_', ' ')}")
        return {}


def _spec_problem(problems: list[Problem]) -> Any:
    def say(message: str) -> None:
        problems.append(Problem(0, 0, message))

    return say


def _check_thing(
    say: Any,
    key: str,
    letter: str,
    name: str,
    letter_case: Any,
    used: set[str],
    existing: dict[str, str],
) -> None:
    if len(letter) != 1 or not letter.isalpha() or not letter_case(letter):
        case = "lower-case" if letter_case is str.islower else "capital"
        say(f"{key}.{letter}: a map letter here is one {case} letter")
    elif letter in existing or letter in used:
        say(f"{key}.{letter}: the letter {letter!r} already stands for {existing.get(letter)!r}")
    if not THING_NAME.match(name):
        say(f"{key}.{letter}: {name!r} is not a name (lower-case words, up to 30 characters)")
    elif name in existing.values() or name == "dirt":
        say(f"{key}.{letter}: {name!r} is already a name of the domain")


# -- checking -----------------------------------------------------------------------------


def _check(spec: EnvironmentSpec, max_states: int) -> tuple[Environment | None, list[Problem]]:
    problems: list[Problem] = []
    say = _spec_problem(problems)
    if not NAME.match(spec.name):
        say(f"name {spec.name!r}: lower-case letters, digits and '-', starting with a letter")
    if spec.domain not in DOMAIN_NAMES:
        say(f"domain {spec.domain!r} is not one of {', '.join(DOMAIN_NAMES)}")
        return None, problems
    if spec.horizon is not None and (
        isinstance(spec.horizon, bool) or not isinstance(spec.horizon, int) or spec.horizon < 1
    ):
        say(f"horizon {spec.horizon!r} is not a whole number of steps above 0")
    share = spec.max_trapped_start_share
    if isinstance(share, bool) or not isinstance(share, int | float) or not 0 <= share <= 1:
        say(f"max_trapped_start_share {share!r} is not a share from 0 to 1")
    options = spec._options(problems)
    grid_map, map_problems = read_map(spec.name, spec.map)
    problems += map_problems
    if grid_map is None:
        return None, sorted(problems)
    # Problems of the definition's keys, the size or the gravity rule leave nothing to build;
    # with those of the text and the cells alone, the rest of the map is built and checked too.
    blocked = any(problem.line == 0 for problem in problems)
    letters, features = _letters(spec.domain, options)
    fields = set(options["rules"].terrains[1:]) if spec.domain == "farming" else set()
    grid_map = _check_cells(grid_map, spec.domain, letters, fields, problems)
    states = grid_map.height * grid_map.width * features
    if states > max_states:
        problems.append(
            Problem(
                *grid_map.where((0, 0)),
                f"the map has {states} states ({grid_map.width} x {grid_map.height} cells, width "
                f"x height, {features} states each), more than the {max_states} the study allows",
            )
        )
        blocked = True
    if spec.domain == "gravity":
        blocked |= _check_gravity_rule(spec, grid_map, options["colours"], problems)
        mapping = {**grid_map.gravity_of_colour, **spec.gravity}
        grid_map = replace(grid_map, gravity_of_colour=mapping)
    blocked |= _check_starts(grid_map, spec.domain, letters, problems)
    if blocked or not grid_map.tasks:
        return None, sorted(problems)
    module = {"navigation": navigation, "gravity": gravity, "farming": farming}[spec.domain]
    try:
        environment = module.build(spec.name, grid_map, spec.horizon, **options)
    except ValueError as error:  # a rule the checks above missed: still one clear problem
        return None, [Problem(1, 1, str(error))]
    _check_reach(environment, grid_map, spec.max_trapped_start_share, problems)
    return (None if problems else environment), sorted(problems)


def _letters(domain: str, options: dict[str, Any]) -> tuple[dict[str, str], int]:
    """The domain's letters {letter: meaning} and the number of features per cell."""
    if domain == "navigation":
        return {navigation.WALL: "wall", navigation.FLOOR: "floor"}, 1
    if domain == "gravity":
        return {gravity.PLAIN: "plain cell", **options["colours"]}, len(gravity.GRAVITIES)
    rules: farming.Rules = options["rules"]
    return {**rules.terrain_of_letter, **rules.machine_of_letter}, len(rules.features)


def _check_cells(
    grid_map: GridMap,
    domain: str,
    letters: dict[str, str],
    fields: set[str],
    problems: list[Problem],
) -> GridMap:
    """Unknown letters, goals on cells that cannot be goals, study starts outside navigation
    (``fields``: the field terrains of a farming map). Returns the map without them (unknown
    letters drawn '.', those tasks and study starts left out) for the checks that follow."""
    goal_letters = set() if domain == "farming" else set(grid_map.goal_letters)
    grid = [list(row) for row in grid_map.grid]
    bad_tasks: set[str] = set()
    legend = ", ".join(f"{letter} {meaning}" for letter, meaning in letters.items())
    for cell in grid_map.cells():
        char = grid_map.char(cell)
        if char not in letters and char not in goal_letters:
            problems.append(
                Problem(
                    *grid_map.where(cell),
                    f"unknown character {char!r} at (row {cell[0]}, column {cell[1]}); "
                    f"a {domain} map draws {legend}"
                    + ("" if domain == "farming" else ", or a task's goal letter"),
                )
            )
            grid[cell[0]][cell[1]] = "."
    for task in grid_map.tasks:
        place = grid_map.place(f"task {task.name}")
        chars = {grid_map.char(cell) for cell in task.goal_cells}
        count = len(problems)
        if domain == "farming":
            kinds = {letters.get(char, repr(char)) for char in chars}
            if len(kinds) != 1 or not kinds <= fields:
                problems.append(
                    Problem(
                        *place,
                        f"task {task.name!r} must cover one field terrain, not "
                        f"{', '.join(sorted(kinds))}",
                    )
                )
        elif domain == "navigation" and navigation.WALL in chars:
            problems.append(Problem(*place, f"the goal of task {task.name!r} is a wall"))
        elif domain == "gravity" and chars & (set(letters) - {gravity.PLAIN}):
            problems.append(Problem(*place, f"the goal of task {task.name!r} is coloured"))
        if len(problems) > count:
            bad_tasks.add(task.name)
    if domain != "navigation":
        for task_name in grid_map.study_starts:
            problems.append(
                Problem(
                    *grid_map.place(f"study-start {task_name}"),
                    f"{domain} maps have no study starts (every task starts in the start region)",
                )
            )
    return replace(
        grid_map,
        grid=tuple("".join(row) for row in grid),
        tasks=tuple(task for task in grid_map.tasks if task.name not in bad_tasks),
        goal_letters=grid_map.goal_letters if domain != "farming" else frozenset(),
        study_starts=grid_map.study_starts if domain == "navigation" else {},
    )


def _check_starts(
    grid_map: GridMap, domain: str, letters: dict[str, str], problems: list[Problem]
) -> bool:
    """Each task's start region has a cell to start on (navigation: a free cell; farming: a
    dirt cell without a machine; gravity: any cell); whether some has none."""
    count = len(problems)
    regions = {
        task.name: grid_map.study_starts.get(task.name, grid_map.start) for task in grid_map.tasks
    }
    for task_name, region in regions.items():
        if domain == "navigation":
            cells = [c for c in grid_map.cells() if grid_map.char(c) != navigation.WALL]
        elif domain == "farming":
            cells = [c for c in grid_map.cells() if letters.get(grid_map.char(c)) == "dirt"]
        else:
            cells = list(grid_map.cells())
        if not any(cell in region for cell in cells):
            key = f"study-start {task_name}" if task_name in grid_map.study_starts else "start"
            problems.append(
                Problem(
                    *grid_map.place(key),
                    f"task {task_name!r}: the start region has no start cell",
                )
            )
    return len(problems) > count


def _check_gravity_rule(
    spec: EnvironmentSpec, grid_map: GridMap, colours: dict[str, str], problems: list[Problem]
) -> bool:
    """Each colour of the map has a gravity, and each gravity a colour; whether not."""
    count = len(problems)
    mapping = {**grid_map.gravity_of_colour, **spec.gravity}
    present: dict[str, tuple[int, int]] = {}
    for cell in grid_map.cells():
        colour = colours.get(grid_map.char(cell))
        if colour is not None and colour not in present:
            present[colour] = cell
    if not present:
        problems.append(
            Problem(*grid_map.where((0, 0)), "a gravity map needs at least one coloured cell")
        )
    for colour, cell in present.items():
        if colour not in mapping:
            problems.append(
                Problem(
                    *grid_map.where(cell),
                    f"no gravity for {colour} (add 'gravity of {colour}: north' or "
                    f"gravity.{colour} = 'north')",
                )
            )
    for colour, direction in mapping.items():
        place = grid_map.places.get(f"gravity of {colour}", (0, 0))
        if colour not in present:
            problems.append(Problem(*place, f"gravity of {colour}: no {colour} cell on the map"))
        elif direction not in DIRECTIONS:
            problems.append(
                Problem(
                    *place,
                    f"gravity of {colour}: {direction!r} is not one of {', '.join(DIRECTIONS)}",
                )
            )
    return len(problems) > count


def _check_reach(
    environment: Environment, grid_map: GridMap, max_trapped: float, problems: list[Problem]
) -> None:
    """Starts that cannot reach a goal within the horizon, trapped starts above the share the
    study accepts (``max_trapped``), and machines no start reaches."""
    true = environment.true_transitions
    features = environment.num_features
    starts_all = np.zeros(environment.num_states, dtype=bool)
    for number, task in enumerate(environment.tasks):
        start_place = grid_map.place(
            f"study-start {task.name}" if task.name in grid_map.study_starts else "start"
        )
        starts = task.start > 0
        starts_all |= starts
        if not starts.any():
            problems.append(
                Problem(*start_place, f"task {task.name!r}: the start region has no start cell")
            )
            continue
        reaches = can_reach(true, task.reward > 0, environment.horizon)
        # A start cell is cut off when no start state of it (any gravity) reaches the goal.
        cell_starts = starts.reshape(-1, features).any(axis=1)
        cell_reaches = (reaches & starts).reshape(-1, features).any(axis=1)
        cut_off = np.flatnonzero(cell_starts & ~cell_reaches)
        if len(cut_off) == int(cell_starts.sum()):
            problems.append(
                Problem(
                    *grid_map.place(f"task {task.name}"),
                    f"task {task.name!r}: no goal cell can be reached from the start region "
                    f"within the horizon of {environment.horizon} steps",
                )
            )
            continue
        trapped = _check_traps(environment, grid_map, number, max_trapped, problems)
        # A cell whose every start is trapped is named by the trap's problem already.
        cut_off = np.array([cell for cell in cut_off if cell not in trapped], dtype=np.int64)
        if len(cut_off):
            first = divmod(int(cut_off[0]), environment.width)
            problems.append(
                Problem(
                    *grid_map.where(first),
                    f"the start region is cut off from the goal of task {task.name!r}: "
                    f"{len(cut_off)} start cell{'s' * (len(cut_off) != 1)} cannot reach it "
                    f"within {environment.horizon} steps, the first at (row {first[0]}, "
                    f"column {first[1]})",
                )
            )
    if not starts_all.any():
        return
    reached = np.asarray(reachable_from(true, starts_all).reshape(-1, features).any(axis=1))
    for item in environment.layout["machines"]:
        cell = (item["row"], item["column"])
        if not reached[cell[0] * environment.width + cell[1]]:
            problems.append(
                Problem(
                    *grid_map.where(cell),
                    f"the {item['machine']} at (row {cell[0]}, column {cell[1]}) can never be "
                    "reached from the start region",
                )
            )


def _check_traps(
    environment: Environment,
    grid_map: GridMap,
    task: int,
    max_trapped: float,
    problems: list[Problem],
) -> set[int]:
    """The task's trapped starts, a problem when the simulations' or the user study's start
    distribution puts more than ``max_trapped`` of its probability on them; the cells (row x
    width + column) whose every start is trapped, if the problem is reported."""
    traps = trapped_states(environment, task)
    share = max(traps.start_share, traps.study_start_share)
    if share <= max_trapped or not len(traps.starts):
        return set()
    chosen = environment.tasks[task]
    starts = (chosen.start > 0) | (chosen.study_start_distribution > 0)
    trapped = np.zeros(environment.num_states, dtype=bool)
    trapped[traps.starts] = True
    features = environment.num_features
    # Cells whose every start is trapped: no share accepted lets a start cell be cut off.
    cell_starts = starts.reshape(-1, features).any(axis=1)
    whole = cell_starts & ~(starts & ~trapped).reshape(-1, features).any(axis=1)
    shares = f"{traps.start_share:.1%} of the simulations' start probability"
    if traps.study_start_share > 0:
        shares += f", {traps.study_start_share:.1%} of the user study's"
    remedy = "give them a way out (in gravity, a colour they can reach) or start elsewhere"
    if not whole.any():
        remedy += f", or accept them: max_trapped_start_share = {math.ceil(share * 100) / 100:g}"
    problems.append(
        Problem(
            *grid_map.where(environment.cell_of(int(traps.starts[0]))),
            f"task {traps.task!r}: {len(traps.starts)} of its {traps.start_states} start states "
            f"({shares}) can never reach its goal, whatever the agent does "
            f"({traps.named(environment, traps.starts)}): {remedy}",
        )
    )
    return {int(cell) for cell in np.flatnonzero(whole)}
