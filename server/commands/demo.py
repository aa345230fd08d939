"""``bam-study demo``: a whole study end to end on this machine.

A study server starts on a new SQLite database in the output folder; simulated participants
take the paper's study over HTTP (arrival, consent, tutorial, six agents each, completion);
once every learner update has finished the data is exported and analysed, and Table 1 is
printed. Everything stays in the folder: the database, the server's log, the export and the
analysis.
"""

from __future__ import annotations

import argparse
import secrets
import shlex
import shutil
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

from server.cores import available_cores

if TYPE_CHECKING:
    from server.app.storage.db import Database

PROG = "bam-study demo"
DEFAULT_SEED = 0
POLL_SECONDS = 0.5


class DemoError(RuntimeError):
    """The demo cannot go on; the message says why and where to look."""


@dataclass(frozen=True)
class DemoOptions:
    out: Path
    participants: int = 8
    concurrency: int = 4
    seed: int = DEFAULT_SEED
    rounds: tuple[int, int] = (3, 5)
    mistake_probability: float = 0.05
    workers: int = 0  # learner-update processes (0: one per core)
    learner_settings: str = ""  # TOML appended to the shipped study configuration


def configure(parser: argparse.ArgumentParser) -> None:
    from server.commands.teach import parse_rounds

    parser.add_argument(
        "--out",
        type=Path,
        default=Path("bam-demo"),
        help="new or empty folder for the database, export and analysis (default: bam-demo)",
    )
    parser.add_argument(
        "--participants",
        type=int,
        default=8,
        help="simulated participants, half per domain (default 8: four sessions per cell)",
    )
    parser.add_argument(
        "--concurrency", type=int, default=4, help="participants at a time (default 4)"
    )
    parser.add_argument(
        "--seed",
        type=int,
        default=DEFAULT_SEED,
        help="seed of the simulated teachers and of the server's random choices: the same "
        f"seed gives the same results (default {DEFAULT_SEED})",
    )
    parser.add_argument(
        "--rounds",
        type=parse_rounds,
        default=(3, 5),
        help="rounds of demonstrations per agent, N or N-M (default 3-5)",
    )
    parser.add_argument(
        "--mistake-probability",
        type=float,
        default=0.05,
        help="the simulated teachers' chance of a random move (default 0.05)",
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=0,
        help="learner-update processes of the server (default: one per core)",
    )


def run(args: argparse.Namespace) -> int:
    options = DemoOptions(
        out=args.out,
        participants=args.participants,
        concurrency=args.concurrency,
        seed=args.seed,
        rounds=args.rounds,
        mistake_probability=args.mistake_probability,
        workers=args.workers,
    )
    try:
        check(options)
    except DemoError as error:
        print(f"{PROG}: error: {error}", file=sys.stderr)
        return 2
    try:
        table = run_demo(options)
    except DemoError as error:
        print(f"{PROG}: error: {error}", file=sys.stderr)
        return 1
    print()
    print(table)
    print(
        f"Seed {options.seed} (`--seed` draws others): these figures come from "
        f"{options.participants} simulated participant{'s' if options.participants != 1 else ''}, "
        "not from people, and differ from the paper's."
    )
    print()
    print(f"The study's database, server log, export and analysis are in {options.out}/:")
    print(f"  {options.out / 'study.sqlite'}   the database (`bam-study serve` can reopen it)")
    print(f"  {options.out / 'export'}/         the CSV export with its data dictionary")
    print(f"  {options.out / 'analysis'}/       Table 1, the appendix tables, comparisons, plots")
    print()
    print("To look at the participants, learning curves and replays in the dashboard:")
    print(
        f"  BAM_DATABASE_URL=sqlite:///{options.out.resolve() / 'study.sqlite'} "
        f"BAM_STUDY_CONFIG={options.out.resolve() / 'study.toml'} "
        f"BAM_ADMIN_TOKEN={secrets.token_urlsafe()} {shlex.quote(bam_study_command())} serve"
    )
    print("  then open http://127.0.0.1:8000/dashboard and sign in with that token.")
    return 0


def bam_study_command() -> str:
    """The absolute path of this ``bam-study`` (in a virtual environment that need not be
    active where the printed command runs), or ``python -m server.commands.main`` with this Python."""
    program = Path(sys.argv[0])
    if program.name == "bam-study" and program.exists():
        return str(program.resolve())
    found = shutil.which("bam-study", path=str(Path(sys.executable).parent))
    if found:
        return str(Path(found).resolve())
    return f"{sys.executable} -m server.commands.main"


def check(options: DemoOptions) -> None:
    if options.participants < 1:
        raise DemoError(f"--participants must be at least 1, got {options.participants}")
    if options.seed < 0:
        raise DemoError(f"--seed must be 0 or more, got {options.seed}")
    if options.concurrency < 1:
        raise DemoError(f"--concurrency must be at least 1, got {options.concurrency}")
    if not 0.0 <= options.mistake_probability <= 1.0:
        raise DemoError(
            f"--mistake-probability must be in [0, 1], got {options.mistake_probability}"
        )
    if options.workers < 0:
        raise DemoError(f"--workers must be 0 (one per core) or more, got {options.workers}")
    out = options.out
    if out.exists() and not out.is_dir():
        raise DemoError(f"--out {out} is a file, not a folder")
    if out.is_dir() and any(out.iterdir()):
        raise DemoError(
            f"--out {out} is not empty; the demo writes a new study there: choose a new folder"
        )


def run_demo(options: DemoOptions, stream: TextIO | None = None) -> str:
    """Run the demo into ``options.out`` (checked by ``check``); returns Table 1 as text."""
    from analysis.data import load_tables as load_export
    from analysis.options import InputError
    from analysis.report import write_outputs
    from analysis.results import analyze
    from analysis.tables import table1_markdown
    from server.app.config import DEFAULT_STUDY_CONFIG
    from server.app.export.tables import load_tables, write_export
    from server.app.storage.db import Database, upgrade
    from server.commands.live import LiveServer
    from server.commands.simulated import TeachingPlan, run_participants
    from server.simulation.progress import Progress

    err = stream if stream is not None else sys.stderr
    out = options.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    url = f"sqlite:///{out / 'study.sqlite'}"
    study = out / "study.toml"
    study.write_text(DEFAULT_STUDY_CONFIG.read_text() + options.learner_settings)
    db = Database.from_url(url)
    try:
        upgrade(db.engine)
        environment = {
            "BAM_DATABASE_URL": url,
            "BAM_STUDY_CONFIG": str(study),
            "BAM_ADMIN_TOKEN": secrets.token_urlsafe(24),
            "BAM_UPDATE_WORKERS": str(options.workers or available_cores()),
            "BAM_SEED": str(options.seed),
        }
        plan = TeachingPlan(
            min_rounds=options.rounds[0],
            max_rounds=options.rounds[1],
            mistake_probability=options.mistake_probability,
            retry_seconds=3600.0,  # an agent try waits for its learner however busy the pool
        )
        print(
            f"{options.participants} simulated participants, {options.concurrency} at a time, "
            f"teach the paper's study on a server at {url}",
            file=err,
            flush=True,
        )
        with LiveServer(out, environment) as server:
            progress = Progress(options.participants, stream=err, label="participants")
            progress.start()
            lock = threading.Lock()

            def finished(_: object) -> None:
                with lock:
                    progress.advance()

            study_run = run_participants(
                server.url,
                options.participants,
                options.concurrency,
                options.seed,
                plan,
                progress=finished,
                in_order=True,
            )
            progress.finish()
            failed = [p for p in study_run.participants if not p.completed]
            if failed:
                first = failed[0]
                raise DemoError(
                    f"{len(failed)} of {options.participants} participants could not finish "
                    f"(participant {first.index}: {first.error}); the server's log is "
                    f"{server.log_path}"
                )
            wait_for_learners(db, err, server.log_path)
        tables = load_tables(db)
    finally:
        db.dispose()
    write_export(tables, out / "export")
    try:
        sessions, evaluations = load_export(out / "export")
        analysis = analyze(sessions, evaluations)
    except InputError as error:  # the export of our own server must always be readable
        raise DemoError(f"the analysis refused the export: {error}") from error
    write_outputs(analysis, out / "analysis")
    return table1_markdown(analysis)


def wait_for_learners(db: Database, err: TextIO, log_path: Path) -> None:
    """Wait until no learner update is pending, with a progress bar over the updates."""
    from sqlalchemy import func, select

    from server.app.storage.models import LearnerUpdate
    from server.simulation.progress import Progress

    def counts() -> tuple[int, int, int]:
        with db.read() as s:
            rows = dict(
                s.execute(
                    select(LearnerUpdate.status, func.count()).group_by(LearnerUpdate.status)
                ).all()
            )
        return int(sum(rows.values())), int(rows.get("pending", 0)), int(rows.get("failed", 0))

    _, pending, _ = counts()
    if pending:
        progress = Progress(pending, stream=err, label="learner updates still to finish")
        progress.start()
        while pending:
            time.sleep(POLL_SECONDS)
            _, now_pending, _ = counts()
            progress.advance(max(0, pending - now_pending))
            pending = now_pending
        progress.finish()
    _, _, failed = counts()
    if failed:
        raise DemoError(f"{failed} learner updates failed; the server's log is {log_path}")
