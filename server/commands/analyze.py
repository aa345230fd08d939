"""``bam-study analyze``: a study's exported data to the paper's Table 1, the appendix p-value
tables, a comparisons CSV and plots."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

from analysis.names import LEARNERS
from analysis.options import (
    DEFAULT_BASELINE,
    DEFAULT_FDR,
    DEFAULT_THRESHOLDS,
    InputError,
    parse_fdr,
    parse_flags,
    parse_thresholds,
)

if TYPE_CHECKING:
    import pandas as pd

PROG = "bam-study analyze"
T = TypeVar("T")


def _argument(parse: Callable[[str], T]) -> Callable[[str], T]:
    """An argparse ``type`` from a parser that raises InputError (argparse then prints
    ``argument --NAME: MESSAGE`` and exits with status 2)."""

    def convert(text: str) -> T:
        try:
            return parse(text)
        except InputError as error:
            raise argparse.ArgumentTypeError(str(error).split(": ", 1)[-1]) from None

    convert.__name__ = parse.__name__
    return convert


def configure(parser: argparse.ArgumentParser) -> None:
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument(
        "--data",
        type=Path,
        metavar="EXPORT_DIR",
        help="folder written by `bam-study export` (sessions.csv, evaluations.csv, "
        "participants.csv)",
    )
    source.add_argument(
        "--database-url",
        metavar="URL",
        help="read the study database directly, e.g. sqlite:///study.sqlite or "
        "postgresql+psycopg://user@host/db",
    )
    parser.add_argument(
        "--out", required=True, type=Path, metavar="DIR", help="folder to write the results to"
    )
    parser.add_argument(
        "--thresholds",
        type=_argument(parse_thresholds),
        default=DEFAULT_THRESHOLDS,
        metavar="T1,T2",
        help="fractions of the optimal return a session must reach (default: 0.5,0.8)",
    )
    parser.add_argument(
        "--fdr",
        type=_argument(parse_fdr),
        default=DEFAULT_FDR,
        help="false discovery rate of the Benjamini-Yekutieli correction (default: 0.2)",
    )
    parser.add_argument(
        "--baseline",
        default=DEFAULT_BASELINE,
        choices=list(LEARNERS),
        help="learner the others are compared with (default: bam)",
    )
    parser.add_argument(
        "--exclude-excluded",
        action="store_true",
        help="drop the sessions of participants the experimenter marked excluded",
    )
    parser.add_argument(
        "--exclude-flagged",
        type=_argument(parse_flags),
        default=(),
        metavar="CHECK[,CHECK]",
        help="drop the sessions of participants any of these quality checks flags "
        "(quality.csv): exceptionally_fast, long_idle, poor_demonstrations, "
        "inconsistent_feedback, failed_attention",
    )
    parser.add_argument(
        "--include-unfinished",
        action="store_true",
        help="also count the taught learning sessions (at least one episode or action) of "
        "participants who did not complete the study (default: only those of participants who did)",
    )
    parser.add_argument(
        "--include-rejected",
        action="store_true",
        help="also count the sessions of participants whose submission was rejected (reviews.csv, "
        "or Prolific's REJECTED); by default they are left out, as work judged invalid",
    )


def run(args: argparse.Namespace) -> int:
    from analysis.data import load_database, load_tables
    from analysis.flow import participant_flow
    from analysis.report import write_outputs
    from analysis.results import analyze
    from analysis.tables import table1_markdown

    notes: list[str] = []
    tables: dict[str, pd.DataFrame | None] = {}
    try:
        if args.database_url is not None:
            sessions, evaluations = load_database(
                args.database_url,
                exclude_excluded=args.exclude_excluded,
                include_unfinished=args.include_unfinished,
                include_rejected=args.include_rejected,
                exclude_flagged=args.exclude_flagged,
                notes=notes,
                tables=tables,
            )
        else:
            sessions, evaluations = load_tables(
                args.data,
                exclude_excluded=args.exclude_excluded,
                include_unfinished=args.include_unfinished,
                include_rejected=args.include_rejected,
                exclude_flagged=args.exclude_flagged,
                notes=notes,
                tables=tables,
            )
        flow = participant_flow(
            tables,
            sessions,
            exclude_excluded=args.exclude_excluded,
            include_rejected=args.include_rejected,
            exclude_flagged=args.exclude_flagged,
            include_unfinished=args.include_unfinished,
        )
        analysis = analyze(
            sessions,
            evaluations,
            thresholds=args.thresholds,
            fdr=args.fdr,
            baseline=args.baseline,
            notes=notes,
            flow=flow,
        )
        written = write_outputs(analysis, args.out)
    except InputError as error:
        print(f"{PROG}: error: {error}", file=sys.stderr)
        return 2
    except OSError as error:
        print(f"{PROG}: error: cannot write the results to {args.out}: {error}", file=sys.stderr)
        return 1
    summary = analysis.summary
    print(table1_markdown(analysis))
    print(
        f"{len(summary)} learning sessions of {summary['participant_id'].nunique()} "
        f"participants in {len(analysis.environments)} environments; "
        f"{analysis.sessions_without_evaluations} without evaluations."
    )
    print(f"Results written to {args.out}: {', '.join(written)}")
    return 0
