"""The participant flow as a CONSORT-style diagram: one box per stage down the left, with an
arrow from each stage to the next and, beside it, a box of those who left on the way and why
(and, with ``--include-unfinished``, those added back); beside the last stage, those counted
all the same though flagged or excluded."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from analysis.flow import ANALYSED, STAGES, FlowBox, ParticipantFlow
from analysis.plots import save_figure
from analysis.selection import count_phrase

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

LINE = 0.27  # height of a line of text, in the diagram's units (inches)
PAD = 0.14
GAP = 0.25  # between a stage box and the box beside the arrow below it
STAGE_X, STAGE_WIDTH = 0.2, 3.4
SIDE_X, SIDE_WIDTH = 4.3, 5.9
WIDTH = 10.4
FONT_SIZE = 9.5


def counts(box: FlowBox) -> str:
    return f"n = {box.participants} ({count_phrase(box.learning_sessions, 'learning session')})"


def _side_lines(title: str, boxes: list[FlowBox]) -> list[str]:
    """A title with the total, then each way with anybody in it (the table lists them all)."""
    shown = [b for b in boxes if b.participants > 0]
    total = sum(b.participants for b in boxes)
    if not shown:
        return [f"{title}: none"]
    return [
        f"{title}: n = {total}",
        *(
            f"  {b.label}: {b.participants} ({count_phrase(b.learning_sessions, 'session')})"
            for b in shown
        ),
    ]


def flow_figure(flow: ParticipantFlow) -> Figure:
    """The diagram of ``flow``; its numbers are the table's (``participant_flow.csv``)."""
    from matplotlib.figure import Figure

    steps = []  # (stage box, lines beside the arrow below it)
    for stage in STAGES:
        leaving = flow.leaving(stage)
        if stage == ANALYSED:
            # Not summed: a participant can be flagged by several checks.
            shown = [b for b in flow.counted(stage) if b.participants > 0]
            beside = ["Counted all the same, though:"] if shown else []
            beside += [
                f"  {b.label}: {b.participants} ({count_phrase(b.learning_sessions, 'session')})"
                for b in shown
            ]
        else:
            beside = _side_lines("Left", [b for b in leaving if b.kind == "left"])
        beside += [
            f"Added back: {b.label}: {b.participants} "
            f"({count_phrase(b.learning_sessions, 'session')})"
            for b in leaving
            if b.kind == "added"
        ]
        steps.append((flow.stage(stage), beside))

    heights = [max(len(beside), 2) * LINE + 2 * PAD + 2 * GAP for _, beside in steps[:-1]]
    stage_height = 2 * LINE + 2 * PAD
    last = steps[-1][1]
    total = len(steps) * stage_height + sum(heights) + max(len(last) * LINE + PAD - stage_height, 0)
    figure = Figure(figsize=(WIDTH, total + 0.6))
    ax = figure.add_axes((0, 0, 1, 1))
    ax.set_xlim(0, WIDTH)
    ax.set_ylim(-0.3 - total, 0.3)
    ax.axis("off")

    top = 0.0
    for number, (box, beside) in enumerate(steps):
        centre = STAGE_X + STAGE_WIDTH / 2
        _box(ax, STAGE_X, top, STAGE_WIDTH, [box.label, counts(box)], bold=True)
        bottom = top - stage_height
        if number == len(steps) - 1:
            if beside:
                _box(ax, SIDE_X, top, SIDE_WIDTH, beside)
                _arrow(
                    ax,
                    (STAGE_X + STAGE_WIDTH, top - stage_height / 2),
                    (SIDE_X, top - stage_height / 2),
                    dashed=True,
                )
            break
        next_top = bottom - heights[number]
        _arrow(ax, (centre, bottom), (centre, next_top))
        middle = (bottom + next_top) / 2
        side_height = len(beside) * LINE + 2 * PAD
        _box(ax, SIDE_X, middle + side_height / 2, SIDE_WIDTH, beside)
        _arrow(ax, (centre, middle), (SIDE_X, middle))
        top = next_top
    return figure


def _box(
    ax: Axes, x: float, top: float, width: float, lines: list[str], bold: bool = False
) -> None:
    from matplotlib.patches import FancyBboxPatch

    height = len(lines) * LINE + 2 * PAD
    ax.add_patch(
        FancyBboxPatch(
            (x, top - height),
            width,
            height,
            boxstyle="round,pad=0,rounding_size=0.08",
            facecolor="#eef3fa" if bold else "white",
            edgecolor="0.25",
            linewidth=1.0,
        )
    )
    for row, line in enumerate(lines):
        ax.text(
            x + (width / 2 if bold else 0.15),
            top - PAD - (row + 0.5) * LINE,
            line,
            ha="center" if bold else "left",
            va="center",
            fontsize=FONT_SIZE,
            fontweight="bold" if bold and row == 0 else "normal",
        )


def _arrow(
    ax: Axes, start: tuple[float, float], end: tuple[float, float], dashed: bool = False
) -> None:
    ax.annotate(
        "",
        xy=end,
        xytext=start,
        arrowprops={
            "arrowstyle": "-|>",
            "color": "0.25",
            "linewidth": 1.0,
            "linestyle": "--" if dashed else "-",
            "shrinkA": 0,
            "shrinkB": 0,
        },
    )


def save_flow(flow: ParticipantFlow, folder: Path) -> list[Path]:
    """``participant_flow.png`` and ``participant_flow.svg`` in ``folder``."""
    return save_figure(flow_figure(flow), folder, "participant_flow")
