"""``bam-study demo``: a whole study end to end on this machine.

A study server starts on a new SQLite database in the output folder; simulated participants
take the paper's study over HTTP (arrival, consent, tutorial, six agents each, completion);
once every learner update has finished the data is exported (the CSVs, and the release
formats: Croissant, a Frictionless data package, Psych-DS and Parquet with a Hugging Face
card) and analysed, and Table 1 is printed. Everything stays in the folder: the database, the
server's log, the export, the
analysis, and the dashboard's sign-in token (``admin-token``, readable by its owner only, so
that the command printed to open the dashboard shows where the token is, not the token).
"""

from __future__ import annotations

import argparse
import json
import os
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
    import pandas as pd

    from server.app.storage.db import Database
    from server.commands.simulated import ProlificArrival

PROG = "bam-study demo"
DEFAULT_SEED = 0
POLL_SECONDS = 0.5
TOKEN_FILE = "admin-token"  # in the output folder: the dashboard's sign-in token


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
    study: Path | None = None  # a study file to run instead of the paper's
    platform: str = "mturk"  # how the simulated participants arrive: mturk ids, or prolific


def configure(parser: argparse.ArgumentParser) -> None:
    from server.commands.teach import parse_rounds

    parser.add_argument(
        "--study",
        type=Path,
        metavar="STUDY.toml",
        help="run this study file (its own environments included) instead of the paper's",
    )
    parser.add_argument(
        "--platform",
        choices=("mturk", "prolific"),
        default="mturk",
        help="how the simulated participants arrive: with MTurk ids (default), or as Prolific "
        "participants through the server's Prolific replica (the study made and published "
        "there first, each participant sent back to it at the end)",
    )
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
        study=args.study,
        out=args.out,
        participants=args.participants,
        concurrency=args.concurrency,
        seed=args.seed,
        rounds=args.rounds,
        mistake_probability=args.mistake_probability,
        workers=args.workers,
        platform=args.platform,
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
    print(
        f"  {options.out / 'export'}/         the CSV export with its data dictionary, "
        "croissant.json, datapackage.json, psych-ds/ and hugging-face/"
    )
    print(f"  {options.out / 'analysis'}/       Table 1, the appendix tables, comparisons, plots")
    print(f"  {options.out / TOKEN_FILE}     the dashboard's sign-in token (yours only)")
    print()
    for line in dashboard_instructions(options.out.resolve()):
        print(line)
    return 0


def write_admin_token(folder: Path) -> str:
    """A new dashboard token, written to ``folder / TOKEN_FILE`` readable and writable by its
    owner only (created so, never widened from a default mode), and returned."""
    token = secrets.token_urlsafe(24)
    descriptor = os.open(folder / TOKEN_FILE, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(descriptor, "w") as file:
        file.write(token + "\n")
    return token


def dashboard_instructions(out: Path) -> list[str]:
    """How to open the demo's study in the dashboard: a command that reads the token from its
    file (a shell expands it; the token itself is not printed) and where to sign in."""
    token_file = out / TOKEN_FILE
    database_url = f"sqlite:///{out / 'study.sqlite'}"
    command = " ".join(
        [
            f"BAM_DATABASE_URL={shlex.quote(database_url)}",
            f"BAM_STUDY_CONFIG={shlex.quote(str(out / 'study.toml'))}",
            f'BAM_ADMIN_TOKEN="$(cat {shlex.quote(str(token_file))})"',
            shlex.quote(bam_study_command()),
            "serve",
        ]
    )
    return [
        "To look at the participants, learning curves and replays in the dashboard:",
        f"  {command}",
        "  then open http://127.0.0.1:8000/dashboard and sign in with the token in",
        f"  {token_file} (readable by you only).",
    ]


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
    if options.study is not None and not options.study.is_file():
        raise DemoError(f"--study {options.study} is not a file")
    if options.workers < 0:
        raise DemoError(f"--workers must be 0 (one per core) or more, got {options.workers}")
    out = options.out
    if out.exists() and not out.is_dir():
        raise DemoError(f"--out {out} is a file, not a folder")
    if out.is_dir() and any(out.iterdir()):
        raise DemoError(
            f"--out {out} is not empty; the demo writes a new study there: choose a new folder"
        )


def _write_study(options: DemoOptions, out: Path) -> tuple[Path, str]:
    """The demo's study file and its admin token, written into ``out`` (the study's own
    environments registered)."""
    study = out / "study.toml"
    text = study_text(options)
    if options.platform == "prolific":
        text = on_prolific(text)
    text = with_dataset(text)
    study.write_text(text + options.learner_settings)
    admin_token = write_admin_token(out)
    if options.study is not None:
        from server.commands.studies import StudyEnvironmentsError, register_study

        try:  # the simulated participants find the study's environments by name too
            register_study(study)
        except StudyEnvironmentsError as error:
            raise DemoError(str(error)) from None
    return study, admin_token


def run_demo(options: DemoOptions, stream: TextIO | None = None) -> str:
    """Run the demo into ``options.out`` (checked by ``check``); returns Table 1 as text."""
    from analysis.data import load_tables as load_export
    from analysis.flow import participant_flow
    from analysis.options import InputError
    from analysis.report import write_outputs
    from analysis.results import analyze
    from analysis.tables import table1_markdown
    from server.app.export.release import RELEASE_FORMATS, About, write_release
    from server.app.export.tables import export_tables
    from server.app.storage.db import Database, upgrade
    from server.app.study_file import load_study_config
    from server.commands.live import ServerProcess, WarmUpNotice
    from server.commands.simulated import TeachingPlan, run_participants
    from server.simulation.progress import Progress

    err = stream if stream is not None else sys.stderr
    out = options.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    url = f"sqlite:///{out / 'study.sqlite'}"
    study, admin_token = _write_study(options, out)
    db = Database.from_url(url)
    try:
        upgrade(db.engine)
        environment = {
            "BAM_DATABASE_URL": url,
            "BAM_STUDY_CONFIG": str(study),
            "BAM_ADMIN_TOKEN": admin_token,
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
            f"teach {'the paper' if options.study is None else options.study.stem}'s study on "
            f"a server at {url}",
            file=err,
            flush=True,
        )
        starting = ServerProcess(out, environment)
        starting.waiting = WarmUpNotice(err)
        with starting as server:
            prolific = None
            if options.platform == "prolific":
                prolific = publish_on_replica(study, server.url, admin_token, options, err)
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
                prolific=prolific,
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
            wait_for_learners(db, err, server.log_path, options.participants)
        tables = export_tables(db)
    finally:
        db.dispose()
    about = About(tables, load_study_config(study))
    write_release(about, out / "export", ("csv", *RELEASE_FORMATS))
    try:
        read: dict[str, pd.DataFrame | None] = {}
        sessions, evaluations = load_export(out / "export", tables=read)
        analysis = analyze(sessions, evaluations, flow=participant_flow(read, sessions))
    except InputError as error:  # the export of our own server must always be readable
        raise DemoError(f"the analysis refused the export: {error}") from error
    write_outputs(analysis, out / "analysis")
    return table1_markdown(analysis)


# What the demo's study says for Prolific (a rehearsal on the server's own replica: the
# public address is a stand-in, the study link is the demo server's own).
PROLIFIC_COMPLETION = """[completion]
mode = "prolific"
prolific_code = "C1DEMO01"
prolific_no_consent_code = "C0DEMO00"
"""
PROLIFIC_TABLE = """
[prolific]
name = "Teach a robot (a rehearsal)"
description = "Teach simulated robots in a grid world with the arrow keys."
places = {places}
reward = 6.00
estimated_minutes = 30
maximum_minutes = 90
public_url = "https://study.example.org"
"""


def on_prolific(text: str) -> str:
    """The study file's text for a run on the Prolific replica: its ``[completion]`` table in
    Prolific's mode, and a ``[prolific]`` table unless it has one."""
    import re

    table = re.compile(r"^\[completion\][^\n]*\n(?:(?!\[)[^\n]*\n?)*", re.MULTILINE)
    if table.search(text):
        text = table.sub(lambda _: PROLIFIC_COMPLETION + "\n", text, count=1)
    elif re.search(r"^\s*completion\s*[.=]", text, re.MULTILINE):
        raise DemoError(
            "--platform prolific: the study file sets its completion without a [completion] "
            "table; write it as one"
        )
    else:
        text = text.rstrip("\n") + "\n\n" + PROLIFIC_COMPLETION
    if not re.search(r"^\[prolific\]", text, re.MULTILINE):
        text = text.rstrip("\n") + "\n" + PROLIFIC_TABLE.format(places=1000)
    return text


# What the demo's release says that only its authors know: its participants are simulated.
DEMO_DATASET = """
[dataset]
limitations = "Every participant of this dataset is simulated (bam-study demo): no person took \
part, and its figures say nothing of people."
"""


def with_dataset(text: str) -> str:
    """The study file's text with the demo's ``[dataset]`` table, unless it has one."""
    import re

    if re.search(r"^\[dataset\]", text, re.MULTILINE):
        return text
    return text.rstrip("\n") + "\n" + DEMO_DATASET


def publish_on_replica(
    study: Path, url: str, admin_token: str, options: DemoOptions, err: TextIO
) -> ProlificArrival:
    """Make the study on the server's Prolific replica and publish it; how the simulated
    participants arrive there."""
    from server.app.platforms.prolific import ProlificClient, ProlificRefused, draft_study
    from server.app.study_file import StudyConfigError, load_study_config
    from server.commands.simulated import ProlificArrival

    try:
        config = load_study_config(study)
        draft = draft_study(config, max_concurrent=options.concurrency, base_url=url)
    except (StudyConfigError, ValueError) as error:
        raise DemoError(f"--platform prolific: {error}") from None
    draft["total_available_places"] = max(
        int(draft["total_available_places"]), options.participants
    )
    client = ProlificClient(f"{url}/prolific/api/v1", admin_token)
    try:
        made = client.create_study(draft)
        client.transition_study(made["id"], "PUBLISH")
    except ProlificRefused as refused:
        raise DemoError(f"the Prolific replica refused the demo's study: {refused}") from None
    finally:
        client.close()
    print(f"the study is {made['id']} on the server's Prolific replica", file=err, flush=True)
    return ProlificArrival(made["id"], admin_token)


def study_text(options: DemoOptions) -> str:
    """The study file the demo runs (the paper's by default), its map files' paths made
    absolute so that the copy in the output folder reads them."""
    import re

    from server.app.study_file import DEFAULT_STUDY_CONFIG

    if options.study is None:
        return DEFAULT_STUDY_CONFIG.read_text()
    base = options.study.resolve().parent
    return re.sub(
        r'^(\s*map_file\s*=\s*)"([^"]*)"',
        lambda match: f"{match.group(1)}{json.dumps(str(base / match.group(2)))}",
        options.study.read_text(encoding="utf-8"),
        flags=re.MULTILINE,
    )


def wait_for_learners(db: Database, err: TextIO, log_path: Path, participants: int) -> None:
    """Wait until no learner update is pending: the participants have finished, but the
    learners may still be training on their last demonstrations and feedback. A line says so,
    then a progress bar counts those updates as they finish."""
    from sqlalchemy import func, select

    from server.app.storage.models import LearnerUpdate
    from server.app.storage.vocabulary import UpdateStatus
    from server.simulation.progress import Progress

    def counts() -> tuple[int, int, int]:
        with db.read() as s:
            rows = dict(
                s.execute(
                    select(LearnerUpdate.status, func.count()).group_by(LearnerUpdate.status)
                ).all()
            )
        return (
            int(sum(rows.values())),
            int(rows.get(UpdateStatus.PENDING, 0)),
            int(rows.get(UpdateStatus.FAILED, 0)),
        )

    _, pending, _ = counts()
    if pending:
        print(
            f"All {participants} participants have finished; the learners are still training "
            f"on their last demonstrations and feedback ({pending} learner "
            f"update{'s' if pending != 1 else ''} queued). The export waits for them.",
            file=err,
            flush=True,
        )
        progress = Progress(pending, stream=err, label="queued learner updates done")
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
