"""An environment drawn for the researcher (``bam-study check``'s PNG): ``CELL_PIXELS`` a cell,
its rows and columns numbered, every task's goal cells marked with the task's number (1, 2, ...),
the start cells dotted, each gravity colour with its letter and its gravity's arrow, each
machine with its letter, and a legend naming them all.

    >>> from server import domains
    >>> from server.domains.figure import environment_figure
    >>> figure = environment_figure(domains.make("doorway"))  # doctest: +SKIP
    >>> figure.savefig("doorway.png", bbox_inches="tight")    # doctest: +SKIP

The colours are the page's (``drawing.COLOURS``; a study's own kinds in their study's colours).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from server.domains.base import Environment
from server.domains.drawing import COLOURS, label

if TYPE_CHECKING:
    from matplotlib.artist import Artist
    from matplotlib.figure import Figure

CELL_PIXELS = 32
DPI = 100
ARROWS = {"north": "\u2191", "south": "\u2193", "east": "\u2192", "west": "\u2190"}
GOAL = "#ffffff"
OUTLINE = "#111111"
START = "#444444"


def _colours(env: Environment) -> dict[str, str]:
    kinds = env.layout.get("drawing", {}).values()
    return {**COLOURS, **{kind["name"]: kind["colour"] for group in kinds for kind in group}}


def _ink(colour: str) -> str:
    """Black or white, whichever reads on ``colour``."""
    red, green, blue = (int(colour[i : i + 2], 16) / 255 for i in (1, 3, 5))
    return "#000000" if 0.299 * red + 0.587 * green + 0.114 * blue > 0.5 else "#ffffff"


def _goal_numbers(env: Environment) -> dict[tuple[int, int], list[int]]:
    numbers: dict[tuple[int, int], list[int]] = {}
    for number, task in enumerate(env.tasks, start=1):
        for cell in task.goal_cells:
            numbers.setdefault((int(cell[0]), int(cell[1])), []).append(number)
    return numbers


def environment_figure(env: Environment) -> Figure:
    """The figure (see the module docstring); save it with ``bbox_inches="tight"``."""
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch, Rectangle

    colours = _colours(env)
    letter_of = {name: letter for letter, name in env.legend.get("letters", {}).items()}
    inches = CELL_PIXELS / DPI
    figure = Figure(figsize=(max(env.width * inches, 4.0), env.height * inches + 1.0), dpi=DPI)
    axes = figure.add_axes((0.0, 0.0, 1.0, 1.0))
    axes.set_xlim(-0.5, env.width - 0.5)
    axes.set_ylim(env.height - 0.5, -0.5)
    axes.set_aspect("equal")

    def cell(row: int, column: int, colour: str, text: str = "", **style: Any) -> None:
        axes.add_patch(
            Rectangle(
                (column - 0.5, row - 0.5),
                1,
                1,
                facecolor=colour,
                edgecolor="#bbbbbb",
                linewidth=0.5,
                **style,
            )
        )
        if text:
            axes.text(
                column,
                row,
                text,
                ha="center",
                va="center",
                fontsize=9,
                color=_ink(colour),
                fontweight="bold",
            )

    layout = env.layout
    for row, line in enumerate(layout["terrain"]):
        for column, terrain in enumerate(line):
            cell(row, column, colours.get(terrain, COLOURS["floor"]))
    for row, column in layout["walls"]:
        cell(row, column, COLOURS["wall"])
    gravity_of = layout.get("gravity_of_colour", {})
    for item in layout["colours"]:
        arrow = ARROWS.get(gravity_of.get(item["colour"], ""), "")
        cell(
            item["row"],
            item["column"],
            colours[item["colour"]],
            letter_of.get(item["colour"], "") + arrow,
        )
    for item in layout["machines"]:
        cell(
            item["row"],
            item["column"],
            colours[item["machine"]],
            letter_of.get(item["machine"], ""),
        )
    _mark_goals_and_starts(env, axes)
    _label(env, axes)
    handles: list[Artist] = [
        Patch(
            facecolor=GOAL, edgecolor=OUTLINE, linewidth=2, label=f"{number}: goal of {task.name}"
        )
        for number, task in enumerate(env.tasks, start=1)
    ]
    handles += _kind_handles(env, colours, letter_of)
    handles.append(
        Line2D([], [], marker="o", markersize=3, linestyle="", color=START, label="a start cell")
    )
    axes.legend(
        handles=handles,
        loc="upper left",
        bbox_to_anchor=(0.0, -0.02),
        fontsize=8,
        ncol=max(1, min(3, env.width // 5)),
        frameon=False,
    )
    return figure


def _mark_goals_and_starts(env: Environment, axes: Any) -> None:
    """Each goal cell outlined with its tasks' numbers; a dot on each start cell."""
    from matplotlib.patches import Rectangle

    for (row, column), numbers in _goal_numbers(env).items():
        # The cell keeps its terrain: an outline, and the task's number on a white label.
        axes.add_patch(
            Rectangle(
                (column - 0.42, row - 0.42),
                0.84,
                0.84,
                facecolor="none",
                edgecolor=OUTLINE,
                linewidth=2,
            )
        )
        axes.text(
            column,
            row,
            ",".join(map(str, numbers)),
            ha="center",
            va="center",
            fontsize=9 if len(numbers) == 1 else 6,
            fontweight="bold",
            bbox={"boxstyle": "round,pad=0.15", "facecolor": GOAL, "edgecolor": "none"},
        )
    starts = np.zeros(env.num_states, dtype=bool)
    for task in env.tasks:
        starts |= (task.start > 0) | (task.study_start_distribution > 0)
    for flat in np.flatnonzero(starts.reshape(-1, env.num_features).any(axis=1)):
        row, column = divmod(int(flat), env.width)
        axes.plot(column + 0.3, row + 0.3, "o", markersize=2.5, color=START)


def _label(env: Environment, axes: Any) -> None:
    """Rows and columns numbered, and the title with the size (width x height)."""
    axes.set_xticks(range(env.width))
    axes.set_yticks(range(env.height))
    axes.tick_params(
        labelsize=7, length=0, top=True, labeltop=True, bottom=False, labelbottom=False
    )
    axes.set_xlabel("column")
    axes.xaxis.set_label_position("top")
    axes.set_ylabel("row")
    axes.set_title(
        f"{env.name} ({env.domain}): {env.width} x {env.height} cells (width x height)",
        fontsize=10,
        pad=24,
    )


def _kind_handles(
    env: Environment, colours: dict[str, str], letter_of: dict[str, str]
) -> list[Artist]:
    """Legend entries for the walls, terrains, gravity colours and machines on the map."""
    from matplotlib.patches import Patch

    layout = env.layout
    handles: list[Artist] = []
    if layout["walls"]:
        handles.append(Patch(facecolor=COLOURS["wall"], label="wall"))
    terrains = sorted({terrain for line in layout["terrain"] for terrain in line})
    if len(terrains) > 1:
        handles += [
            Patch(facecolor=colours[name], edgecolor="#bbbbbb", label=label(name))
            for name in terrains
        ]
    gravity_of = layout.get("gravity_of_colour", {})
    for colour, gravity in gravity_of.items():
        text = f"{letter_of.get(colour, '')} {label(colour)}: sets gravity {gravity}"
        handles.append(Patch(facecolor=colours[colour], label=text))
    works_on = env.legend.get("works_on", {})
    for machine in dict.fromkeys(item["machine"] for item in layout["machines"]):
        text = f"{letter_of.get(machine, '')} {label(machine)}"
        if machine in works_on:
            text += f" (enters {works_on[machine]})"
        handles.append(Patch(facecolor=colours[machine], label=text))
    return handles
