"""The tables of docs/reproduction.md, from the curves the simulation runs wrote.

    python scripts/reproduction_tables.py docs/reproduction/demonstrations [more folders]

For each experiment folder (holding `curves.csv` from `bam-study simulate`): per environment,
each learner's percent of the optimal total return at rounds 1, 3, 5 and 10 (mean and standard
error over agents); BAM minus each other learner, averaged over the rounds (the area between
the curves) and at the last round, with the standard error of a difference of two independent
means; and the share of agents still below 50% at the last round.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd

from analysis.names import ENVIRONMENTS, LEARNERS

ROUNDS = (1, 3, 5, 10)


def mean_se(values: pd.Series) -> tuple[float, float]:
    values = values.to_numpy(dtype=float)
    se = values.std(ddof=1) / np.sqrt(len(values)) if len(values) > 1 else float("nan")
    return float(values.mean()), float(se)


def experiment_tables(folder: Path) -> str:
    curves = pd.read_csv(folder / "curves.csv")
    experiment = str(curves["experiment"].iloc[0])
    learners = [name for name in LEARNERS if name in set(curves["learner"])]
    last = int(curves["round"].max())
    rounds = sorted({r for r in ROUNDS if r <= last} | {last})
    agents = curves.groupby(["environment", "learner"])["agent"].nunique()
    lines = [
        f"### {experiment}: percent of the optimal total return (mean ± s.e. over "
        f"{int(agents.min())}-{int(agents.max())} agents)",
        "",
        "| Environment | Learner | " + " | ".join(f"Round {r}" for r in rounds) + " |",
        "|---|---|" + "---:|" * len(rounds),
    ]
    environments = [name for name in ENVIRONMENTS if name in set(curves["environment"])]
    for environment in environments:
        for learner in learners:
            rows = curves[(curves["environment"] == environment) & (curves["learner"] == learner)]
            cells = []
            for r in rounds:
                mean, se = mean_se(100 * rows.loc[rows["round"] == r, "normalized_return"])
                cells.append(f"{mean:.1f} ± {se:.1f}")
            lines.append(
                f"| {ENVIRONMENTS[environment]} | {LEARNERS[learner]} | " + " | ".join(cells) + " |"
            )
    others = [name for name in learners if name != "bam"]
    if "bam" not in learners or not others:
        return "\n".join(lines) + "\n"
    lines += [
        "",
        f"### {experiment}: BAM against each other learner",
        "",
        f"BAM minus the other learner in percentage points (mean ± s.e. of the difference): "
        f"averaged over rounds 1-{last} (the area between the curves, per round), and at "
        f"round {last}. Positive: BAM is ahead.",
        "",
        "| Environment | "
        + " | ".join(
            f"vs {LEARNERS[o]}, rounds 1-{last} | vs {LEARNERS[o]}, round {last}" for o in others
        )
        + " |",
        "|---|" + "---:|" * (2 * len(others)),
    ]
    for environment in environments:
        rows = curves[(curves["environment"] == environment) & (curves["round"] >= 1)]
        per_agent = rows.groupby(["learner", "agent"])["normalized_return"].mean() * 100
        final = rows[rows["round"] == last].set_index(["learner", "agent"])["normalized_return"]
        final = final * 100
        cells = []
        for other in others:
            cells.append(_difference(per_agent["bam"], per_agent[other]))
            cells.append(_difference(final["bam"], final[other]))
        lines.append(f"| {ENVIRONMENTS[environment]} | " + " | ".join(cells) + " |")
    lines += [
        "",
        f"### {experiment}: agents far from the optimum at round {last}",
        "",
        f"Share of agents below 50% of the optimal total return at round {last}.",
        "",
        "| Environment | " + " | ".join(LEARNERS[name] for name in learners) + " |",
        "|---|" + "---:|" * len(learners),
    ]
    for environment in environments:
        final = curves[(curves["environment"] == environment) & (curves["round"] == last)]
        shares = final.groupby("learner")["normalized_return"].apply(lambda v: (v < 0.5).mean())
        lines.append(
            f"| {ENVIRONMENTS[environment]} | "
            + " | ".join(f"{100 * shares[name]:.0f}%" for name in learners)
            + " |"
        )
    return "\n".join(lines) + "\n"


def _difference(bam: pd.Series, other: pd.Series) -> str:
    difference = bam.mean() - other.mean()
    se = np.sqrt(bam.var(ddof=1) / len(bam) + other.var(ddof=1) / len(other))
    return f"{difference:+.1f} ± {se:.1f}"


def main(argv: list[str]) -> int:
    if not argv:
        print(__doc__, file=sys.stderr)
        return 2
    for folder in argv:
        print(experiment_tables(Path(folder)))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
