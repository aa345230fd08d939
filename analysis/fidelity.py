"""Did a change alter what agents learn? Two runs of one simulated-teacher experiment (the
``curves.csv`` that ``bam-study simulate`` writes) set side by side, cell by cell.

A cell is one (environment, learner, round): the mean percent of the optimal total return over
a run's agents. Its difference between the runs is counted in units of its standard error, that
of a difference of two independent means (conservative when both runs taught the same agents,
as runs with one seed do: their curves are then positively correlated). Chance alone puts about
one cell in twenty beyond 2 of those units; the agents are taken as changed when more than one
cell in ten is beyond 2 (``MAX_SHARE_BEYOND_2``), or any beyond 3 (``MAX_UNITS``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from analysis.names import ENVIRONMENTS, LEARNERS, environment_display
from analysis.options import InputError

MAX_SHARE_BEYOND_2 = 0.1
MAX_UNITS = 3.0
COLUMNS = ("environment", "learner", "agent", "round", "normalized_return")


@dataclass(frozen=True)
class Cell:
    environment: str
    learner: str
    round: int
    reference_mean: float  # percent of the optimal total return
    reference_se: float
    reference_agents: int
    run_mean: float
    run_se: float
    run_agents: int

    @property
    def difference(self) -> float:
        return self.run_mean - self.reference_mean

    @property
    def units(self) -> float:
        """The difference over the standard error of a difference of two independent means;
        0 where both runs agree exactly (every agent alike, no spread), infinite where they
        differ with no spread."""
        se = math.hypot(self.reference_se, self.run_se)
        if se == 0.0:
            return 0.0 if self.difference == 0.0 else math.copysign(math.inf, self.difference)
        return self.difference / se


@dataclass(frozen=True)
class Comparison:
    cells: tuple[Cell, ...]

    @property
    def beyond_2(self) -> int:
        return sum(abs(cell.units) > 2.0 for cell in self.cells)

    @property
    def beyond_3(self) -> int:
        return sum(abs(cell.units) > MAX_UNITS for cell in self.cells)

    @property
    def largest(self) -> Cell:
        return max(self.cells, key=lambda cell: abs(cell.units))

    @property
    def kept(self) -> bool:
        """The agents learn as before: at most one cell in ten beyond 2 units, none beyond 3."""
        return self.beyond_2 <= MAX_SHARE_BEYOND_2 * len(self.cells) and self.beyond_3 == 0


def read_curves(path: Path) -> pd.DataFrame:
    """A run's ``curves.csv`` (the file, or the folder holding it)."""
    file = path / "curves.csv" if path.is_dir() else path
    if not file.is_file():
        raise InputError(f"{path}: no curves.csv (a folder written by `bam-study simulate`)")
    try:
        curves = pd.read_csv(file)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as error:
        raise InputError(f"{file}: not a CSV file ({error})") from None
    missing = [name for name in COLUMNS if name not in curves.columns]
    if missing:
        raise InputError(f"{file}: missing column(s) {', '.join(missing)}")
    values = pd.to_numeric(curves["normalized_return"], errors="coerce")
    if values.isna().any() or not np.isfinite(values.to_numpy(dtype=float)).all():
        raise InputError(f"{file}: normalized_return holds a value that is not a number")
    return curves


def _cells(curves: pd.DataFrame) -> pd.DataFrame:
    grouped = curves.assign(percent=100.0 * curves["normalized_return"]).groupby(
        ["environment", "learner", "round"]
    )["percent"]
    table = grouped.agg(["mean", "count"])
    table["se"] = grouped.std(ddof=1).fillna(0.0) / np.sqrt(table["count"])
    return table


def compare(reference: pd.DataFrame, run: pd.DataFrame) -> Comparison:
    """Every cell both runs have, from round 1 on (round 0 is the untaught agent), in the
    paper's order of environments and learners."""
    first, second = _cells(reference), _cells(run)
    shared = first.index.intersection(second.index)
    shared = [key for key in shared if int(key[2]) >= 1]
    if not shared:
        raise InputError("the two runs share no (environment, learner, round) cell after round 0")

    def order(key: tuple[str, str, int]) -> tuple[int, int, int]:
        environment, learner, round_ = key
        return (
            ENVIRONMENTS.index(environment) if environment in ENVIRONMENTS else len(ENVIRONMENTS),
            list(LEARNERS).index(learner) if learner in LEARNERS else len(LEARNERS),
            int(round_),
        )

    cells = []
    for key in sorted(shared, key=order):
        a, b = first.loc[key], second.loc[key]
        cells.append(
            Cell(
                environment=str(key[0]),
                learner=str(key[1]),
                round=int(key[2]),
                reference_mean=float(a["mean"]),
                reference_se=float(a["se"]),
                reference_agents=int(a["count"]),
                run_mean=float(b["mean"]),
                run_se=float(b["se"]),
                run_agents=int(b["count"]),
            )
        )
    return Comparison(tuple(cells))


def report(comparison: Comparison, reference: str, run: str) -> str:
    """The comparison as Markdown: the verdict, then every cell."""
    cells = comparison.cells
    verdict = (
        "**kept**: the agents learn as in the reference"
        if comparison.kept
        else "**changed**: the agents do not learn as in the reference"
    )
    largest = comparison.largest
    lines = [
        f"Reference: `{reference}`; run: `{run}`.",
        "",
        f"{len(cells)} cells (environment, learner, round); beyond 2 standard errors: "
        f"{comparison.beyond_2} ({comparison.beyond_2 / len(cells):.1%}; chance alone about "
        f"5%, at most {MAX_SHARE_BEYOND_2:.0%} allowed); beyond {MAX_UNITS:g}: "
        f"{comparison.beyond_3} (none allowed). Largest: {environment_display(largest.environment)}, "
        f"{LEARNERS.get(largest.learner, largest.learner)}, round {largest.round}, "
        f"{largest.units:+.2f}. Verdict: {verdict}.",
        "",
        "Percent of the optimal total return, mean ± s.e. over agents; the difference is the "
        "run's minus the reference's, in percentage points and in standard errors of a "
        "difference of two independent means.",
        "",
        "| Environment | Learner | Round | Reference | Run | Difference | In s.e. |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for cell in cells:
        units = f"{cell.units:+.2f}"
        if abs(cell.units) > 2.0:
            units = f"**{units}**"
        lines.append(
            f"| {environment_display(cell.environment)} | {LEARNERS.get(cell.learner, cell.learner)} "
            f"| {cell.round} | {cell.reference_mean:.1f} ± {cell.reference_se:.1f} "
            f"| {cell.run_mean:.1f} ± {cell.run_se:.1f} | {cell.difference:+.1f} "
            f"| {units} |"
        )
    return "\n".join(lines) + "\n"
