"""``bam-study fidelity``: did a change alter what the agents learn? A simulation run's curves
set beside a reference run's, cell by cell (``analysis.fidelity``).

    bam-study simulate --experiment demonstrations --out /tmp/demonstrations
    bam-study fidelity docs/reproduction/demonstrations /tmp/demonstrations --out fidelity.md

Exit status 0 when the agents learn as in the reference, 1 when they changed, 2 on bad input.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from analysis.fidelity import MAX_SHARE_BEYOND_2, MAX_UNITS, compare, read_curves, report
from analysis.options import InputError


def configure(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = (
        "Each cell is one (environment, learner, round) mean over agents; its difference is "
        "counted in standard errors of a difference of two independent means. The agents "
        f"changed when more than {MAX_SHARE_BEYOND_2:.0%} of the cells are beyond 2, or any "
        f"beyond {MAX_UNITS:g}. Exit 0: kept; 1: changed; 2: bad input."
    )
    parser.add_argument(
        "reference", type=Path, help="the reference run's folder (or its curves.csv)"
    )
    parser.add_argument("run", type=Path, help="the run to compare (folder or curves.csv)")
    parser.add_argument(
        "--out", type=Path, metavar="FILE.md", help="also write the comparison to this file"
    )


def run(args: argparse.Namespace) -> int:
    try:
        comparison = compare(read_curves(args.reference), read_curves(args.run))
    except InputError as error:
        print(f"bam-study fidelity: {error}", file=sys.stderr)
        return 2
    text = report(comparison, str(args.reference), str(args.run))
    if args.out is not None:
        try:
            args.out.write_text(text, encoding="utf-8")
        except OSError as error:
            print(f"bam-study fidelity: cannot write {args.out}: {error.strerror}", file=sys.stderr)
            return 2
    print(text, end="")
    return 0 if comparison.kept else 1
