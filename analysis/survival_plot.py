"""Kaplan-Meier curves: per environment and threshold, the share of each learner's taught
sessions that had not yet reached the threshold after each count of episodes (or actions).
A session that stopped without reaching it is censored at its last evaluation (a tick on the
curve); a curve that stays above 1/2 has no median."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from analysis.names import environment_display, learner_display, threshold_label
from analysis.plots import save_figure
from analysis.results import Analysis
from analysis.survival import event_times, kaplan_meier
from server.names import LEARNER_REGISTRY

if TYPE_CHECKING:
    from matplotlib.figure import Figure

AXIS_NAMES = {"episodes": "Episodes", "actions": "Actions"}


def survival_figure(analysis: Analysis, measure: str) -> Figure:
    """One row per threshold, one column per environment."""
    from matplotlib.figure import Figure

    environments, thresholds = analysis.environments, analysis.thresholds
    figure = Figure(
        figsize=(4.2 * len(environments), 3.2 * len(thresholds) + 0.8), layout="constrained"
    )
    axes = figure.subplots(len(thresholds), len(environments), squeeze=False, sharey=True)
    for row, threshold in enumerate(thresholds):
        times = event_times(analysis.summary, analysis.evaluations, measure, threshold)
        for column, environment in enumerate(environments):
            ax = axes[row, column]
            ax.set_title(f"{environment_display(environment)}, {threshold_label(threshold)}%")
            ax.set_xlabel(AXIS_NAMES[measure])
            ax.set_ylim(-0.02, 1.05)
            ax.axhline(0.5, color="0.6", linestyle=":", linewidth=0.9)
            in_environment = times.loc[times["environment"] == environment]
            for learner in analysis.learners:
                sessions = in_environment.loc[in_environment["learner"] == learner]
                if sessions.empty:
                    continue
                _curve(ax, sessions, learner)
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize="small", loc="upper right", frameon=False)
    for ax in axes[:, 0]:
        ax.set_ylabel("Not yet at the threshold")
    figure.suptitle(
        f"Kaplan-Meier estimate of the share of sessions not yet at the threshold, by {measure} "
        "(ticks: sessions that stopped without reaching it)",
        fontsize="medium",
    )
    return figure


def _curve(ax, sessions, learner: str) -> None:  # type: ignore[no-untyped-def]
    times, share = kaplan_meier(sessions)
    end = float(sessions["time"].max())
    x = np.concatenate([[0.0], times, [max(end, times[-1] if len(times) else 0.0)]])
    y = np.concatenate([[1.0], share, [share[-1] if len(share) else 1.0]])
    colour = LEARNER_REGISTRY[learner].colour
    ax.plot(
        x,
        y,
        drawstyle="steps-post",
        color=colour,
        linewidth=1.6,
        label=f"{learner_display(learner)} (n={len(sessions)})",
    )
    censored = sessions.loc[~sessions["event"], "time"].to_numpy(float)
    if len(censored):
        at = np.searchsorted(x, censored, side="right") - 1
        ax.plot(censored, y[at], "|", color=colour, markersize=7)


def save_survival_curves(analysis: Analysis, folder: Path) -> list[Path]:
    """``survival_episodes`` and ``survival_actions`` as PNG and SVG in ``folder``."""
    written = []
    for measure in ("episodes", "actions"):
        written += save_figure(survival_figure(analysis, measure), folder, f"survival_{measure}")
    return written
