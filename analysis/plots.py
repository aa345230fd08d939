"""Learning curves: normalised return against cumulative episodes or actions, the mean and
standard error over a learner's sessions, one panel per environment.

Each session's curve is a step function: at a count x it is the normalised return of the
session's latest evaluation made at a count of at most x (its last evaluation carries forward
to the end of the axis; before its first evaluation it has no value and does not count).
The curves are evaluated on the union of all counts at which any session of the environment
was evaluated, so the means are exact, not binned. The dashboard's live curves compute the same
on the database (``server.app.live.curves``, where the two computations are).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from analysis.names import environment_display, learner_display, threshold_label
from analysis.results import Analysis
from server.app.live.curves import mean_and_standard_error as mean_and_standard_error
from server.app.live.curves import step_values as step_values
from server.names import LEARNER_REGISTRY

if TYPE_CHECKING:
    from matplotlib.figure import Figure

AXIS_NAMES = {"episodes": "Episodes", "actions": "Actions"}


def learning_curve_figure(analysis: Analysis, x: str) -> Figure:
    """The figure of normalised return against ``x`` ("episodes" or "actions")."""
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    environments = analysis.environments
    columns = min(len(environments), 4)
    rows = math.ceil(len(environments) / columns)
    figure = Figure(figsize=(4.2 * columns, 3.4 * rows + 0.8), layout="constrained")
    axes = figure.subplots(rows, columns, squeeze=False, sharey=True)
    evaluations = analysis.evaluations
    for ax, environment in zip(axes.flat, environments, strict=False):
        in_environment = evaluations.loc[evaluations["environment"] == environment]
        ax.set_title(environment_display(environment))
        ax.set_xlabel(AXIS_NAMES[x])
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))  # counts: no 2.5 episodes
        ax.set_ylim(0, 1.05)
        for threshold in analysis.thresholds:
            ax.axhline(threshold, color="0.6", linestyle=":", linewidth=0.9)
        if in_environment.empty:
            ax.text(0.5, 0.5, "no evaluations", ha="center", va="center", transform=ax.transAxes)
            continue
        grid = np.unique(np.concatenate([[0], in_environment[x].to_numpy()]))
        for learner in analysis.learners:
            of_learner = in_environment.loc[in_environment["learner"] == learner]
            if of_learner.empty:
                continue
            ordered = of_learner.sort_values(["session_id", "update_index"], kind="stable")
            values = np.vstack(
                [
                    step_values(group[x].to_numpy(), group["normalized_return"].to_numpy(), grid)
                    for _, group in ordered.groupby("session_id", sort=False)
                ]
            )
            mean, se, _ = mean_and_standard_error(values)
            colour = LEARNER_REGISTRY[learner].colour  # the same in every panel and figure
            ax.plot(
                grid,
                mean,
                drawstyle="steps-post",
                color=colour,
                linewidth=1.6,
                label=f"{learner_display(learner)} (n={len(values)})",
            )
            ax.fill_between(
                grid, mean - se, mean + se, step="post", color=colour, alpha=0.2, linewidth=0
            )
        # Below the panel, outside its axes: inside, it covered curves and error bands.
        ax.legend(
            fontsize="small",
            loc="upper center",
            bbox_to_anchor=(0.5, -0.18),
            frameon=False,
        )
    for ax in axes.flat[len(environments) :]:
        ax.set_visible(False)
    for ax in axes[:, 0]:
        ax.set_ylabel("Normalised return")
    thresholds = ", ".join(f"{threshold_label(t)}%" for t in analysis.thresholds)
    figure.suptitle(
        f"Normalised return against {x}: mean ± standard error over learning sessions "
        f"(dotted: {thresholds})",
        fontsize="medium",
    )
    return figure


def save_figure(figure: Figure, folder: Path, stem: str) -> list[Path]:
    """``figure`` as ``stem``.png and ``stem``.svg in ``folder``; the two paths."""
    import matplotlib

    written = []
    # A fixed salt and no date make the SVG files reproducible.
    with matplotlib.rc_context({"svg.hashsalt": "bam-study"}):
        for suffix in ("png", "svg"):
            path = folder / f"{stem}.{suffix}"
            metadata = {"Date": None} if suffix == "svg" else {}
            figure.savefig(path, dpi=150, metadata=metadata)
            written.append(path)
    return written


def save_learning_curves(analysis: Analysis, folder: Path) -> list[Path]:
    """``return_vs_episodes`` and ``return_vs_actions`` as PNG and SVG in ``folder``."""
    written = []
    for x in ("episodes", "actions"):
        written += save_figure(learning_curve_figure(analysis, x), folder, f"return_vs_{x}")
    return written
