"""Power against participants: one line per test with its 95% interval, the target power
and the test's level drawn across."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from analysis.names import learner_display, threshold_label
from analysis.plots import save_figure
from analysis.power import TARGET, TEST_NAMES


def save_power_figure(
    table: pd.DataFrame,
    folder: Path,
    first: str,
    second: str,
    threshold: float,
    alpha: float,
    no_difference: bool = False,
) -> list[Path]:
    """``power.png`` and ``power.svg`` in ``folder``."""
    from matplotlib.figure import Figure

    figure = Figure(figsize=(7, 4.2), layout="constrained")
    ax = figure.subplots()
    for test, rows in table.groupby("test", sort=False):
        rows = rows.sort_values("participants")
        x = rows["participants"].to_numpy()
        (line,) = ax.plot(x, rows["power"], marker="o", label=TEST_NAMES[str(test)])
        ax.fill_between(x, rows["power_low"], rows["power_high"], color=line.get_color(), alpha=0.2)
    ax.axhline(TARGET, color="grey", linestyle="--", linewidth=1)
    ax.axhline(alpha, color="grey", linestyle=":", linewidth=1)
    ax.set_ylim(0, 1)
    ax.set_xlabel("Participants")
    ax.set_ylabel(f"Power (rejected at {alpha:g}, {learner_display(first)} ahead)")
    case = " (no true difference: outcomes swapped within blocks)" if no_difference else ""
    ax.set_title(
        f"{learner_display(first)} beats {learner_display(second)} at "
        f"{threshold_label(threshold)}%{case}",
        fontsize="medium",
    )
    ax.legend(fontsize="small", loc="lower right")
    return save_figure(figure, folder, "power")
