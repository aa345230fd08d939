"""The paper's simulation figures: a panel per environment, percent of the optimal total
return against rounds, the mean over agents with a standard-error band per learner, and one
legend for the whole figure."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from server import domains, learners
from server.names import LEARNER_REGISTRY
from server.simulation.config import RunConfig
from server.simulation.runner import atomic_write

if TYPE_CHECKING:
    from server.simulation.outputs import SummaryRow

TITLES: dict[str, str] = {
    "demonstrations": "Learning from demonstration",
    "global-cost": "Global cost functions",
    "feedback": "Demonstrations and feedback",
}


def panel_title(name: str) -> str:
    """The paper's caption style: 'Navigation - Two Rooms'."""
    return f"{domains.domain_of(name).capitalize()} - {domains.title(name)}"


def plot_curves(config: RunConfig, summary: Sequence[SummaryRow], stem: Path) -> list[Path]:
    """Draw the figure and write it as ``stem``.png and ``stem``.svg."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    count = len(config.environments)
    columns = min(4, count)
    rows = math.ceil(count / columns)
    figure, axes = plt.subplots(
        rows,
        columns,
        # One environment alone gets the width its title and legend need.
        figsize=(max(3.4 * columns, 6.0), 2.9 * rows + 0.9),
        squeeze=False,
        sharex=True,
        sharey=True,
    )
    handles = {}
    for index, environment in enumerate(config.environments):
        ax = axes[index // columns][index % columns]
        for learner in config.learners:
            points = sorted(
                (row.round, row.mean_normalized_return, row.se_normalized_return)
                for row in summary
                if row.environment == environment and row.learner == learner
            )
            if not points:
                continue
            # One colour and marker per learner, the same in every figure (the registry's).
            colour, marker = LEARNER_REGISTRY[learner].colour, LEARNER_REGISTRY[learner].marker
            x = [p[0] for p in points]
            mean = [100 * p[1] for p in points]
            se = [0.0 if math.isnan(p[2]) else 100 * p[2] for p in points]
            (line,) = ax.plot(
                x,
                mean,
                color=colour,
                marker=marker,
                markersize=3.5,
                linewidth=1.6,
                label=learners.DISPLAY_NAMES.get(learner, learner),
            )
            ax.fill_between(
                x,
                [m - s for m, s in zip(mean, se, strict=True)],
                [m + s for m, s in zip(mean, se, strict=True)],
                color=colour,
                alpha=0.2,
                linewidth=0,
            )
            handles[learner] = line
        ax.set_title(panel_title(environment), fontsize=10)
        ax.set_xlim(0, config.rounds)
        ax.set_ylim(0, 105)
        ax.grid(True, linewidth=0.4, alpha=0.5)
        ax.tick_params(labelsize=8)
        if config.rounds <= 12:
            ax.set_xticks(range(config.rounds + 1))
    for index in range(count, rows * columns):
        axes[index // columns][index % columns].set_visible(False)
    for ax in axes[:, 0]:
        ax.set_ylabel("% of optimal total return", fontsize=9)
    for index in range(count):
        row, column = divmod(index, columns)
        # The bottom panel of each column carries the x label (hidden panels leave a gap).
        if row == rows - 1 or (row + 1) * columns + column >= count:
            axes[row][column].set_xlabel("Rounds", fontsize=9)
            axes[row][column].tick_params(labelbottom=True)
    figure.suptitle(
        f"{TITLES.get(config.experiment, config.experiment)}: mean of {config.agents} "
        f"agent{'' if config.agents == 1 else 's'} "
        "± standard error",
        fontsize=11,
    )
    figure.legend(
        [handles[name] for name in config.learners if name in handles],
        [learners.DISPLAY_NAMES.get(name, name) for name in config.learners if name in handles],
        loc="lower center",
        ncol=len(handles) or 1,
        frameon=False,
        fontsize=9,
    )
    figure.tight_layout(rect=(0, 0.07 if rows == 1 else 0.05, 1, 0.95))
    paths = []
    for suffix, metadata in ((".png", {"Software": None}), (".svg", {"Date": None})):
        path = stem.with_suffix(suffix)

        def save(temporary: Path, suffix: str = suffix, metadata: dict = metadata) -> None:
            figure.savefig(temporary, format=suffix[1:], dpi=150, metadata=metadata)

        atomic_write(path, save)
        paths.append(path)
    plt.close(figure)
    return paths
