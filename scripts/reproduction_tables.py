"""The tables of docs/reproduction.md, from the curves the simulation runs wrote.

    python scripts/reproduction_tables.py docs/reproduction/demonstrations [more folders]

For each experiment folder (holding `curves.csv` from `bam-study simulate`): per environment,
each learner's percent of the optimal total return at rounds 1, 3, 5 and 10 (mean and standard
error over agents); BAM minus each other learner (and model-based IRL with a global cost minus
model-based IRL, where both ran), averaged over the rounds (the area between the curves) and at
the last round, with the standard error of a difference of two independent means; and the share
of agents still below 50% at the last round.

    python scripts/reproduction_tables.py --versus docs/reproduction/demonstrations \
        docs/reproduction/feedback

compares two experiments over the agents they share (the same seed gives the same agents): per
environment and learner, the second experiment's percent of the optimal total return minus the
first's, averaged over the rounds and at the last round (mean ± s.e. of the paired differences),
and for BAM against each other learner how the gap changed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from analysis.names import ENVIRONMENTS, LEARNERS, environment_display

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
                f"| {environment_display(environment)} | {LEARNERS[learner]} | "
                + " | ".join(cells)
                + " |"
            )
    pairs = [("bam", name) for name in learners if name != "bam" and "bam" in learners]
    if "global-cost" in learners and "model-based" in learners:
        pairs.append(("global-cost", "model-based"))
    if not pairs:
        return "\n".join(lines) + "\n"
    lines += [
        "",
        f"### {experiment}: differences between learners",
        "",
        f"The first learner minus the second in percentage points (mean ± s.e. of the "
        f"difference): averaged over rounds 1-{last} (the area between the curves, per round), "
        f"and at round {last}. Positive: the first learner is ahead.",
        "",
        "| Environment | "
        + " | ".join(
            f"{LEARNERS[a]} − {LEARNERS[b]}, rounds 1-{last} | {LEARNERS[a]} − {LEARNERS[b]}, "
            f"round {last}"
            for a, b in pairs
        )
        + " |",
        "|---|" + "---:|" * (2 * len(pairs)),
    ]
    for environment in environments:
        per_agent, final = _per_agent(curves[curves["environment"] == environment], last)
        cells = []
        for a, b in pairs:
            cells.append(_difference(per_agent[a], per_agent[b]))
            cells.append(_difference(final[a], final[b]))
        lines.append(f"| {environment_display(environment)} | " + " | ".join(cells) + " |")
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
            f"| {environment_display(environment)} | "
            + " | ".join(f"{100 * shares[name]:.0f}%" for name in learners)
            + " |"
        )
    return "\n".join(lines) + "\n"


def _per_agent(curves: pd.DataFrame, last: int) -> tuple[pd.Series, pd.Series]:
    """Percent of optimal per (learner, agent): mean over rounds 1..last, and at round last."""
    rows = curves[curves["round"] >= 1]
    per_agent = rows.groupby(["learner", "agent"])["normalized_return"].mean() * 100
    final = rows[rows["round"] == last].set_index(["learner", "agent"])["normalized_return"] * 100
    return per_agent, final


def versus_tables(first_folder: Path, second_folder: Path) -> str:
    """The second experiment minus the first, over the agents both ran (paired by agent)."""
    first = pd.read_csv(first_folder / "curves.csv")
    second = pd.read_csv(second_folder / "curves.csv")
    names = (str(first["experiment"].iloc[0]), str(second["experiment"].iloc[0]))
    if names[0] == names[1]:  # two runs of one experiment (other settings): name the folders
        names = (first_folder.name, second_folder.name)
    agents = set(first["agent"]) & set(second["agent"])
    first = first[first["agent"].isin(agents)]
    second = second[second["agent"].isin(agents)]
    last = int(min(first["round"].max(), second["round"].max()))
    learners = [name for name in LEARNERS if name in set(first["learner"]) & set(second["learner"])]
    environments = [
        name
        for name in ENVIRONMENTS
        if name in set(first["environment"]) & set(second["environment"])
    ]
    lines = [
        f"### {names[1]} minus {names[0]}, paired by agent ({len(agents)} agents)",
        "",
        f"Percentage points (mean ± s.e. of the paired differences), averaged over rounds "
        f"1-{last} and at round {last}. Positive: the agent did better in {names[1]}.",
        "",
        "| Environment | "
        + " | ".join(
            f"{LEARNERS[n]}, rounds 1-{last} | {LEARNERS[n]}, round {last}" for n in learners
        )
        + " |",
        "|---|" + "---:|" * (2 * len(learners)),
    ]
    gaps = []
    for environment in environments:
        a_mean, a_last = _per_agent(first[first["environment"] == environment], last)
        b_mean, b_last = _per_agent(second[second["environment"] == environment], last)
        cells = []
        for learner in learners:
            cells.append(_paired(b_mean[learner], a_mean[learner]))
            cells.append(_paired(b_last[learner], a_last[learner]))
        lines.append(f"| {environment_display(environment)} | " + " | ".join(cells) + " |")
        if "bam" in learners and len(learners) > 1:
            row = []
            for other in (n for n in learners if n != "bam"):
                gap_a = _paired(a_mean["bam"], a_mean[other])
                gap_b = _paired(b_mean["bam"], b_mean[other])
                row.append(f"{gap_a} | {gap_b}")
            gaps.append(f"| {environment_display(environment)} | " + " | ".join(row) + " |")
    if gaps:
        others = [n for n in learners if n != "bam"]
        lines += [
            "",
            f"BAM minus each other learner, rounds 1-{last}, over the same agents in both "
            f"experiments (paired by agent).",
            "",
            "| Environment | "
            + " | ".join(
                f"vs {LEARNERS[o]}, {names[0]} | vs {LEARNERS[o]}, {names[1]}" for o in others
            )
            + " |",
            "|---|" + "---:|" * (2 * len(others)),
            *gaps,
        ]
    return "\n".join(lines) + "\n"


def _paired(after: pd.Series, before: pd.Series) -> str:
    common = after.index.intersection(before.index)
    differences = (after[common] - before[common]).to_numpy(dtype=float)
    se = differences.std(ddof=1) / np.sqrt(len(differences))
    return f"{differences.mean():+.1f} ± {se:.1f}"


def _difference(bam: pd.Series, other: pd.Series) -> str:
    difference = bam.mean() - other.mean()
    se = np.sqrt(bam.var(ddof=1) / len(bam) + other.var(ddof=1) / len(other))
    return f"{difference:+.1f} ± {se:.1f}"


def experiment_folder(text: str) -> Path:
    """An argument naming a folder that holds a simulation's curves.csv."""
    folder = Path(text)
    if not (folder / "curves.csv").is_file():
        raise argparse.ArgumentTypeError(
            f"{text!r} holds no curves.csv (give the --out folder of `bam-study simulate`)"
        )
    return folder


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog="Tables in Markdown on standard output.",
    )
    parser.add_argument("folders", nargs="+", type=experiment_folder, metavar="FOLDER")
    parser.add_argument(
        "--versus",
        action="store_true",
        help="compare two experiment folders over the agents they share (paired by agent)",
    )
    args = parser.parse_args(argv)
    if args.versus:
        if len(args.folders) != 2:
            parser.error("--versus takes exactly two experiment folders")
        print(versus_tables(*args.folders))
        return 0
    for folder in args.folders:
        print(experiment_tables(folder))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
