"""``bam-study power``: how many participants a study needs to see one learner beat another.

    bam-study power --compare bam cloning --threshold 0.8 --out /tmp/power
    bam-study power --study server/examples/office-study.toml --compare bam cloning \\
        --participants 4,8,16 --bank 10 --studies 500 --out /tmp/office-power

Simulated participants of varied skill teach the study's agents once (the bank, kept in --out
and reused by a run with the same arguments); many studies of each size are resampled from
them and analysed with the planned tests (docs/analysis.md, "Power").
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from analysis.options import DEFAULT_THRESHOLDS, InputError, parse_thresholds

if TYPE_CHECKING:
    import pandas as pd

    from analysis.power_bank import BankPlan

PROG = "bam-study power"
DEFAULT_PARTICIPANTS = (8, 16, 24, 32, 48, 64)


def _counts(text: str) -> tuple[int, ...]:
    try:
        values = tuple(int(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: give whole numbers separated by commas, for example 8,16,24"
        ) from None
    if not values or min(values) < 1 or len(set(values)) != len(values):
        raise argparse.ArgumentTypeError(
            f"{text!r}: each number of participants at least 1, none twice"
        )
    return tuple(sorted(values))


def _rounds(text: str) -> tuple[int, int]:
    low, _, high = text.partition("-")
    try:
        values = (int(low), int(high or low))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give N or N-M, for example 3-5") from None
    if not 1 <= values[0] <= values[1]:
        raise argparse.ArgumentTypeError(f"{text!r}: give N or N-M with 1 <= N <= M")
    return values


def _thresholds(text: str) -> tuple[float, ...]:
    try:
        return parse_thresholds(text)
    except InputError as error:
        raise argparse.ArgumentTypeError(str(error).split(": ", 1)[-1]) from None


def configure(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = (
        "prints the power of each test at each number of participants and the fewest "
        "participants for 80% power; writes power.csv, power.png, power.svg and the bank "
        "(power_bank.json, power_bank.jsonl) in --out"
    )
    parser.add_argument(
        "--study", type=Path, metavar="STUDY.toml", help="the study file (default: the paper's)"
    )
    parser.add_argument(
        "--compare",
        nargs=2,
        metavar=("FIRST", "SECOND"),
        default=("bam", "cloning"),
        help="the two learners: the power to see FIRST beat SECOND (default: bam cloning)",
    )
    parser.add_argument(
        "--threshold", type=float, default=0.8, help="the threshold compared (default 0.8)"
    )
    parser.add_argument(
        "--thresholds",
        type=_thresholds,
        default=DEFAULT_THRESHOLDS,
        metavar="T1,T2",
        help="the study's thresholds, as analyze takes them (default: 0.5,0.8)",
    )
    parser.add_argument(
        "--participants",
        type=_counts,
        default=DEFAULT_PARTICIPANTS,
        metavar="N1,N2,...",
        help="numbers of participants (default: 8,16,24,32,48,64)",
    )
    parser.add_argument(
        "--studies",
        type=int,
        default=2000,
        help="simulated studies at each number of participants (default 2000)",
    )
    parser.add_argument(
        "--bank",
        type=int,
        default=24,
        metavar="N",
        help="simulated participants per domain whose sessions are simulated (default 24)",
    )
    parser.add_argument(
        "--rounds",
        type=_rounds,
        default=(3, 5),
        metavar="N-M",
        help="rounds of teaching per agent, drawn per participant (default 3-5)",
    )
    parser.add_argument("--alpha", type=float, default=0.05, help="the tests' level (default 0.05)")
    parser.add_argument(
        "--no-difference",
        action="store_true",
        help="swap the two learners' outcomes at random within each block: the power is then "
        "the tests' level (a check of the method on the same bank)",
    )
    parser.add_argument(
        "--seed", type=int, default=0, help="seed of every random stream (default 0)"
    )
    parser.add_argument(
        "--jobs", type=int, default=None, help="local worker processes (default: all cores)"
    )
    parser.add_argument(
        "--out", required=True, type=Path, metavar="DIR", help="folder of the bank and results"
    )


def error(message: str) -> int:
    print(f"{PROG}: error: {message}", file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    from analysis.names import learner_display, threshold_label
    from analysis.power_bank import BankPlan, Population, check_bank_folder
    from server.app.study_file import StudyConfigError, load_study_config
    from server.cores import available_cores
    from server.simulation.config import ConfigError

    try:
        study = load_study_config(args.study)
    except StudyConfigError as problem:
        return error(str(problem))
    first, second = args.compare
    for name in (first, second):
        if name not in study.learners:
            return error(
                f"--compare: {name!r} is not a learner of the study; its learners: "
                f"{', '.join(study.learners)}"
            )
    if first == second:
        return error("--compare: give two different learners")
    if args.threshold not in args.thresholds:
        return error(
            f"--threshold {args.threshold:g} is not one of the study's thresholds "
            f"({', '.join(f'{t:g}' for t in args.thresholds)}); add it to --thresholds"
        )
    for name, value in (("--studies", args.studies), ("--bank", args.bank)):
        if value < 1:
            return error(f"{name} must be at least 1, got {value}")
    if not (math.isfinite(args.alpha) and 0 < args.alpha < 1):
        return error(f"--alpha must be in (0, 1), got {args.alpha:g}")
    workers = available_cores() if args.jobs is None else args.jobs
    if workers < 1:
        return error(f"--jobs must be at least 1, got {workers}")
    if args.seed < 0:
        return error(f"--seed must be a non-negative integer, got {args.seed}")
    study.register_environments()
    plan = BankPlan(
        domains=tuple((d.name, tuple(d.environments)) for d in study.domains),
        learners=(first, second),
        participants=args.bank,
        seed=args.seed,
        population=Population(rounds=args.rounds),
        settings=tuple(
            (name, tuple(sorted(study.settings_of(name).items()))) for name in study.learners
        ),
    )
    try:
        check_bank_folder(args.out, plan)
    except ConfigError as problem:
        return error(str(problem))
    table = compute(args, plan, workers)
    print_table(table, first, second, args.threshold, args.alpha, args.no_difference)
    label = threshold_label(args.threshold)
    from analysis.power import participants_needed

    needed = participants_needed(table, "mcnemar_midp")
    largest = max(args.participants)
    if needed is None:
        best = table.loc[
            (table["test"] == "mcnemar_midp") & (table["participants"] == largest), "power"
        ]
        print(
            f"80% power to see {learner_display(first)} beat {learner_display(second)} at "
            f"{label}% (exact McNemar mid-p, alpha {args.alpha:g}): not reached with up to "
            f"{largest} participants (power {float(best.iloc[0]):.2f} at {largest}); try more "
            "with --participants"
        )
    else:
        print(
            f"80% power to see {learner_display(first)} beat {learner_display(second)} at "
            f"{label}% (exact McNemar mid-p, alpha {args.alpha:g}): {needed} participants "
            f"(of {', '.join(map(str, args.participants))})"
        )
    return 0


def compute(args: argparse.Namespace, plan: BankPlan, workers: int) -> pd.DataFrame:
    """The bank (simulated where missing), the power table, its CSV and figures."""
    from analysis.names import learner_display, threshold_label
    from analysis.power import bank_blocks, power_table, reach_shares
    from analysis.power_bank import build_bank
    from analysis.power_plot import save_power_figure
    from server.learners.compile_notice import compile_notice
    from server.simulation.progress import Progress

    first, second = args.compare
    sessions = len(plan.jobs())
    print(
        f"bank: {plan.participants} simulated participants per domain, {sessions} sessions",
        file=sys.stderr,
    )
    bar: list[Progress] = []

    def advance(done: int, total: int) -> None:
        if not bar:
            bar.append(Progress(total, done, stream=sys.stderr, label="sessions"))
            bar[0].start()
        elif done > bar[0].done:
            bar[0].advance(done - bar[0].done)

    try:
        with compile_notice(sys.stderr, PROG, "the first sessions"):
            bank = build_bank(plan, args.out, workers, advance)
    finally:
        if bar:
            bar[0].finish()
    blocks = bank_blocks(bank, first, second, args.threshold)
    shares = reach_shares(blocks)
    print(
        f"In the bank, {learner_display(first)} reached {threshold_label(args.threshold)}% in "
        f"{shares[0]:.0%} of the sessions and {learner_display(second)} in {shares[1]:.0%}."
    )
    studies = Progress(len(args.participants), stream=sys.stderr, label="study sizes")
    studies.start()
    table = power_table(
        blocks,
        args.participants,
        args.studies,
        args.seed,
        alpha=args.alpha,
        no_difference=args.no_difference,
        advance=studies.advance,
    )
    studies.finish()
    table.to_csv(args.out / "power.csv", index=False, float_format="%.6g")
    written = save_power_figure(
        table, args.out, first, second, args.threshold, args.alpha, args.no_difference
    )
    print(
        f"wrote {args.out / 'power.csv'}, {', '.join(str(path) for path in written)}",
        file=sys.stderr,
    )
    return table


def print_table(
    table: pd.DataFrame,
    first: str,
    second: str,
    threshold: float,
    alpha: float,
    no_difference: bool,
) -> None:
    from analysis.names import learner_display, threshold_label
    from analysis.power import TEST_NAMES

    case = "; no true difference (outcomes swapped within blocks)" if no_difference else ""
    print(
        f"Power to see {learner_display(first)} beat {learner_display(second)} at "
        f"{threshold_label(threshold)}% (rejected at {alpha:g}, {learner_display(first)} "
        f"ahead){case}:"
    )
    header = (
        f"{'participants':>12}  {'test':<52} {'power':>6}  {'95% interval':<13} {'rejections':>10}"
    )
    print(header)
    for row in table.itertuples(index=False):
        print(
            f"{row.participants:>12}  {TEST_NAMES[row.test]:<52} {row.power:>6.3f}  "
            f"{row.power_low:.3f}-{row.power_high:.3f}  {row.rejections:>10.3f}"
        )
