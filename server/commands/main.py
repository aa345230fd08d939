"""The ``bam-study`` console command: one subcommand per job a user runs.

Each subcommand lives in its own module exposing ``configure(parser)`` and ``run(args) -> int``;
modules are imported only when their subcommand runs, so ``bam-study --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

# name -> (module, one-line help)
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "demo": (
        "server.commands.demo",
        "Run a whole study end to end: server, simulated participants, export, Table 1.",
    ),
    "analyze": (
        "server.commands.analyze",
        "Turn a study's data (export or database) into the paper's tables and plots.",
    ),
    "simulate": (
        "server.commands.simulate",
        "Run the paper's simulated-teacher experiments and write curves, figures and a report.",
    ),
    "fidelity": (
        "server.commands.fidelity",
        "Set a simulation run's curves beside a reference run's: did the agents change?",
    ),
    "serve": ("server.commands.serve", "Run the study server (settings from BAM_* variables)."),
    "db": ("server.commands.db", "Create or upgrade the study database's schema (migrations)."),
    "export": ("server.commands.export", "Export the study's data as CSV files with a dictionary."),
    "erase": (
        "server.commands.erase",
        "Erase one participant's data on their request (by number, worker id or pseudonym).",
    ),
    "teach": ("server.commands.teach", "Run simulated participants against a study server."),
    "prolific": (
        "server.commands.prolific",
        "Make the study on Prolific from the study file, publish, pause, add places, status.",
    ),
    "power": (
        "server.commands.power",
        "How many participants a study needs: power by simulated teachers, against participants.",
    ),
    "check": (
        "server.commands.check",
        "Check a study file before running it: problems, drawings, optimal returns, update times.",
    ),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="bam-study",
        description="BAM Study: interactive-learning user studies with Behavior Aware Modeling.",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    subparsers.required = True
    for name, (module_name, help_text) in SUBCOMMANDS.items():
        sub = subparsers.add_parser(name, help=help_text, description=help_text)
        module = importlib.import_module(module_name)
        module.configure(sub)
        sub.set_defaults(_module=module_name)
    return parser


def subcommand_parser(
    parser: argparse.ArgumentParser, argv: Sequence[str]
) -> argparse.ArgumentParser:
    """The parser of the deepest subcommand ``argv`` names (``prolific create``'s, say)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for word in argv:
                if word in action.choices:
                    return subcommand_parser(action.choices[word], argv[argv.index(word) + 1 :])
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    words = list(sys.argv[1:] if argv is None else argv)
    args, unknown = parser.parse_known_args(words)
    if unknown:  # said by the subcommand's parser, with its usage, not the top level's
        subcommand_parser(parser, words).error(f"unrecognized arguments: {' '.join(unknown)}")
    module = importlib.import_module(args._module)
    try:
        return int(module.run(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
