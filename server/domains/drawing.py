"""What the page needs to draw an environment's kinds of cell and machine: for each terrain,
machine and gravity colour, its name, its name for people and its colour.

The built-in ones keep the page's own colours (``COLOURS``, the fills of
``server/static/js/grid.js``, which also has their patterns and pictures); a study's own take
theirs from the study file's ``colours`` table, else one of ``SPARE_COLOURS`` (a study's colour
for a built-in name is not used: the built-in kinds look the same everywhere). The page draws
a colour it has no pattern for with a pattern of its own and the name or initial beside it,
so that no kind is told apart by its colour alone.

    >>> from server import domains
    >>> domains.make("two-fields").layout["drawing"]["machines"][0]
    {'name': 'plow', 'label': 'Plow', 'colour': '#6b7785', 'built_in': True, 'terrain': 'soil'}
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from itertools import cycle
from typing import Any

# The page's own colours (grid.js: TERRAIN, GRAVITY_COLOURS and the machines' pictures).
COLOURS: dict[str, str] = {
    "floor": "#f7f5f0",
    "wall": "#2f3542",
    "dirt": "#ecdcbc",
    "soil": "#9a6a3f",
    "grass": "#a8d88f",
    "crops": "#e6bb45",
    "orange": "#E69F00",
    "green": "#009E73",
    "purple": "#CC79A7",
    "plow": "#6b7785",
    "sprinkler": "#56B4E9",
    "harvester": "#F0E442",
}
# For a study's own kind the study file gives no colour: in turn, Okabe and Ito's blue and
# vermillion, then greys.
SPARE_COLOURS: tuple[str, ...] = ("#0072B2", "#D55E00", "#7f7f7f", "#4d4d4d", "#b3b3b3")


def label(name: str) -> str:
    """A kind's name for people: 'vines' -> 'Vines', 'sky blue' -> 'Sky blue'."""
    return name[:1].upper() + name[1:]


def drawing(
    terrains: Iterable[str],
    machines: Mapping[str, str] | None = None,
    colours: Iterable[str] = (),
    palette: Mapping[str, str] | None = None,
) -> dict[str, list[dict[str, Any]]]:
    """The ``drawing`` key of an environment's layout: ``terrains``, ``machines`` and
    ``colours`` (gravity), each a list of ``{"name", "label", "colour", "built_in"}``;
    ``machines`` {machine: the terrain it works on} adds ``terrain`` to each machine and
    ``machines`` (those that enter it) to each terrain. ``palette``: the study's {name: "#rrggbb"}."""
    palette = dict(palette or {})
    machines = dict(machines or {})
    spare = cycle(SPARE_COLOURS)

    def kind(name: str) -> dict[str, Any]:
        # A built-in kind looks the same in every environment: the page has its pattern.
        built_in = name in COLOURS
        colour = COLOURS[name] if built_in else palette.get(name) or next(spare)
        return {"name": name, "label": label(name), "colour": colour, "built_in": built_in}

    return {
        "terrains": [
            {**kind(terrain), "machines": [m for m, t in machines.items() if t == terrain]}
            if machines
            else kind(terrain)
            for terrain in terrains
        ],
        "machines": [
            {**kind(machine), "terrain": terrain} for machine, terrain in machines.items()
        ],
        "colours": [kind(colour) for colour in colours],
    }
