"""The environments' layouts equal the reference maps (environments.md, copied here verbatim:
the reference file is not part of the repository), rendered back to text from ``describe()``
the way the browser page reads them."""

from __future__ import annotations

import json
from typing import Any

import pytest

from server import domains

# The eight maps of the reference, verbatim (column digits and row numbers included).
REFERENCE_MAPS: dict[str, str] = {
    "wall": """
    012345678
  0 A..###..B
  1 ...###...
  2 ...###...
  3 ...###...
  4 ...###...
  5 ...###...
  6 .........
  7 .........
  8 .........
""",
    "doorway": """
    01234567890
  0 ...........
  1 .B.......A.
  2 ...........
  3 ###.....###
  4 ...........
  5 .D.......C.
  6 ...........
  7 #####.#####
  8 ...........
  9 ...........
 10 ...........
""",
    "two-rooms": """
    012345678901234
  0 B..#########..A
  1 ...#...#...#...
  2 .....C.#.......
  3 ...#...#...#...
  4 ...#########...
  5 ...............
  6 ...............
  7 ...............
""",
    "three-rooms": """
    0123456789012
  0 .............
  1 .............
  2 ..#########..
  3 ..#.......#..
  4 .............
  5 ..#.......#..
  6 A.#########.B
  7 ..#...#...#..
  8 ......#......
  9 ..#...#...#..
 10 ..#########..
 11 .............
 12 .............
""",
    "flip": """
    0123456789
  0 .o..o...o.
  1 ..........
  2 ..........
  3 ..........
  4 A........B
  5 ..........
  6 ..........
  7 ..........
  8 ..........
  9 .g..g...g.
""",
    "choices": """
    012345678901234
  0 .g..o.....o..p.
  1 ...............
  2 ...............
  3 A.............B
""",
    "two-fields": """
    012345678901
  0 ............
  1 .ss.........
  2 .ss.W.......
  3 ..........P.
  4 ............
  5 .cc.H.......
  6 .cc.........
  7 ............
""",
    "three-fields": """
    012345678901
  0 ............
  1 .ss.....ss..
  2 .ss.W...ss..
  3 ............
  4 ............
  5 .ii......P..
  6 .ii.........
  7 ............
""",
}

# The reference's true (hidden) colour mappings and farming task fields.
GRAVITY_OF_COLOUR = {
    "flip": {"orange": "south", "green": "north"},
    "choices": {"orange": "south", "green": "north", "purple": "north"},
}


def block(rows: range, columns: range) -> set[tuple[int, int]]:
    return {(r, c) for r in rows for c in columns}


FARMING_GOALS = {
    "two-fields": {
        "Soil field": block(range(1, 3), range(1, 3)),
        "Crops field": block(range(5, 7), range(1, 3)),
    },
    "three-fields": {"Soil field": block(range(1, 3), range(1, 3))},
}

TERRAIN_LETTER = {"floor": ".", "dirt": ".", "soil": "s", "grass": "i", "crops": "c"}
MACHINE_LETTER = {"plow": "P", "sprinkler": "W", "harvester": "H"}
COLOUR_LETTER = {"orange": "o", "green": "g", "purple": "p"}


def reference_grid(text: str) -> list[str]:
    """The reference drawing without its column digits and row numbers."""
    lines = [line for line in text.splitlines() if line.strip()]
    header, rows = lines[0].strip(), lines[1:]
    assert header == "".join(str(c % 10) for c in range(len(header)))
    assert [int(line.split()[0]) for line in rows] == list(range(len(rows)))
    return [line.split()[1] for line in rows]


def render(description: dict[str, Any]) -> list[str]:
    """Draw an environment from its JSON description with the reference's letters: walls '#',
    terrain, machines, colours, and the goal of each single-letter task as its letter."""
    height, width = description["height"], description["width"]
    terrain = description["terrain"]
    assert len(terrain) == height and all(len(row) == width for row in terrain)
    grid = [[TERRAIN_LETTER[kind] for kind in row] for row in terrain]
    for row, column in description["walls"]:
        grid[row][column] = "#"
    for machine in description["machines"]:
        grid[machine["row"]][machine["column"]] = MACHINE_LETTER[machine["machine"]]
    for colour in description["colours"]:
        grid[colour["row"]][colour["column"]] = COLOUR_LETTER[colour["colour"]]
    for task in description["tasks"]:
        if len(task["name"]) == 1:
            for row, column in task["goal_cells"]:
                assert grid[row][column] == ".", "a letter goal is drawn on a free cell"
                grid[row][column] = task["name"]
    return ["".join(row) for row in grid]


@pytest.mark.parametrize("name", domains.ENVIRONMENTS)
def test_layout_equals_reference_map(name: str) -> None:
    description = domains.make(name).describe()
    assert render(description) == reference_grid(REFERENCE_MAPS[name])


@pytest.mark.parametrize("name", domains.NAMES)
def test_description_is_plain_json(name: str) -> None:
    description = domains.make(name).describe()
    # A round trip through JSON changes tuples and NumPy scalars, so equality proves plain types.
    assert json.loads(json.dumps(description)) == description
    assert {"walls", "terrain", "machines", "colours", "gravity_of_colour"} <= description.keys()


@pytest.mark.parametrize("name", ["flip", "choices", "gravity-tutorial"])
def test_true_colour_mapping(name: str) -> None:
    expected = GRAVITY_OF_COLOUR["flip" if name == "gravity-tutorial" else name]
    assert domains.make(name).describe()["gravity_of_colour"] == expected


@pytest.mark.parametrize("name", ["two-fields", "three-fields"])
def test_farming_task_fields(name: str) -> None:
    description = domains.make(name).describe()
    goals = {
        task["name"]: {tuple(cell) for cell in task["goal_cells"]} for task in description["tasks"]
    }
    assert goals == FARMING_GOALS[name]


def test_navigation_tutorial_features() -> None:
    description = domains.make("navigation-tutorial").describe()
    assert (description["height"], description["width"]) == (11, 11)
    walls = block(range(3, 4), range(3, 8)) | block(range(7, 8), range(3, 8))
    walls |= {(4, 3), (4, 7), (6, 3), (6, 7)}
    assert {tuple(cell) for cell in description["walls"]} == walls
    assert [(task["name"], task["goal_cells"]) for task in description["tasks"]] == [
        ("Top", [[0, 5]]),
        ("Bottom", [[10, 5]]),
    ]
    assert description["machines"] == [] and description["colours"] == []


def test_farming_tutorial_features() -> None:
    description = domains.make("farming-tutorial").describe()
    assert (description["height"], description["width"]) == (10, 12)
    fields = {
        "soil": block(range(1, 3), range(1, 3)) | block(range(5, 7), range(9, 11)),
        "grass": block(range(1, 3), range(5, 7)) | block(range(5, 7), range(1, 3)),
        "crops": block(range(1, 3), range(9, 11)),
    }
    terrain = description["terrain"]
    for kind, cells in fields.items():
        assert {(r, c) for r in range(10) for c in range(12) if terrain[r][c] == kind} == cells
    assert {(r, c) for r in range(10) for c in range(12) if terrain[r][c] == "dirt"} == (
        block(range(10), range(12)) - set().union(*fields.values())
    )
    assert description["machines"] == [
        {"row": 8, "column": 2, "machine": "plow"},
        {"row": 8, "column": 4, "machine": "sprinkler"},
        {"row": 8, "column": 6, "machine": "harvester"},
    ]
    goals = {
        task["name"]: {tuple(cell) for cell in task["goal_cells"]} for task in description["tasks"]
    }
    assert list(goals) == ["Soil", "Grass", "Crops"]
    assert goals == {
        "Soil": block(range(1, 3), range(1, 3)),
        "Grass": block(range(1, 3), range(5, 7)),
        "Crops": block(range(1, 3), range(9, 11)),
    }
    assert description["walls"] == [] and description["colours"] == []


def test_gravity_tutorial_is_the_flip_layout() -> None:
    tutorial = domains.make("gravity-tutorial").describe()
    flip = domains.make("flip").describe()
    assert tutorial.pop("name") == "gravity-tutorial"
    assert flip.pop("name") == "flip"
    assert tutorial == flip
