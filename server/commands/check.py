"""``bam-study check STUDY.toml``: is a study ready to run, before anyone is paid?

    bam-study check server/examples/office-study.toml --out /tmp/office-check

Prints every problem of the study file (its maps' with their line and column, trapped starts
among them: ``server.domains.reachability``) and stops there (exit status 2) if it has any;
a Prolific study (completion mode ``prolific``) that loads but that Prolific would refuse or
that speaks of MTurk to Prolific's participants (``prolific_problems``) stops there too
(exit status 1);
else, for each environment the study teaches, its size (width x height), a drawing in the map's
letters (and a PNG in ``--out``: ``server.domains.figure``), each task's optimal return, its
traps (starts and reachable states from which its goal can never be reached; a warning for
reachable ones), and each learner's expected update time on this machine, estimated from the
environment's size (states x actions x horizon x tasks) and the processor time of one update
per learner on the paper's doorway, with a warning where it exceeds ``UPDATE_SECONDS_CAPACITY``;
and which questions of the data's release its ``[dataset]`` table leaves open (the export lists
them as not answered).
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from server.app.study_file import StudyConfig
    from server.domains.base import Environment

PROG = "bam-study check"
# The update time a study can serve: a participant waits for an update between rounds, and a
# longer wait than this, several participants at once, is more than the server can take.
UPDATE_SECONDS_CAPACITY = 2.0
CALIBRATION_ENVIRONMENT = "doorway"
# Words a Prolific participant would not understand: MTurk's own (a worker, a HIT, the requester).
MTURK_WORDING = re.compile(
    r"\b(Mechanical Turk|MTurk|Amazon Turk|HITs?|worker ?ID|workerId|requester)\b", re.IGNORECASE
)
# Study-file tables whose strings are not shown to participants as text.
NOT_PARTICIPANT_TEXT = (
    "completion",
    "environments",
    "domains",
    "colours",
    "learner_settings",
    "dataset",  # the release's, for its readers
)


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("study", type=Path, metavar="STUDY.toml", help="the study file")
    parser.add_argument(
        "--out",
        type=Path,
        metavar="DIR",
        help="where to write each environment's drawing as NAME.png (default: STUDY-check "
        "beside the current folder's files)",
    )


def size(env: Environment) -> int:
    """The environment's size for an update: states x actions x horizon x tasks."""
    return env.num_states * env.num_actions * env.horizon * len(env.tasks)


def text_drawing(env: Environment) -> list[str]:
    """The grid in the map's letters, goal cells drawn as their task's number (1, 2, ...)."""
    letter_of = {name: letter for letter, name in env.legend.get("letters", {}).items()}
    rows = [[letter_of.get(terrain, ".") for terrain in line] for line in env.layout["terrain"]]
    for row, column in env.layout["walls"]:
        rows[row][column] = letter_of.get("wall", "#")
    for item in env.layout["colours"]:
        rows[item["row"]][item["column"]] = letter_of.get(item["colour"], "?")
    for item in env.layout["machines"]:
        rows[item["row"]][item["column"]] = letter_of.get(item["machine"], "?")
    for number, task in enumerate(env.tasks, start=1):
        for row, column in task.goal_cells:
            rows[row][column] = str(number % 10)
    header = "    " + "".join(str(column % 10) for column in range(env.width))
    return [header, *(f"{row:>3} {''.join(cells)}" for row, cells in enumerate(rows))]


def calibrate(learner_names: tuple[str, ...]) -> dict[str, float]:
    """Seconds of one update per unit of size, per learner, timed here on the doorway with a
    demonstration per task (after an untimed first update, which compiles the planner)."""
    from server import domains, learners
    from server.teacher import Teacher

    env = domains.make(CALIBRATION_ENVIRONMENT)
    teacher = Teacher(env, seed=0)
    rng = np.random.default_rng(0)
    rates = {}
    for name in learner_names:
        learner = learners.make(name, env, seed=0)
        timed = 0.0
        for attempt in range(2):
            for task in range(len(env.tasks)):
                for step in teacher.demonstration(task, env.sample_start(task, rng)):
                    learner.record_demonstration(task, *step)
            # Processor time, not wall time: other work on the machine does not count.
            started = time.process_time()
            learner.update()
            timed = time.process_time() - started if attempt else 0.0
        rates[name] = timed / size(env)
    return rates


def run(args: argparse.Namespace) -> int:
    from server import domains
    from server.app.study_file import StudyConfigError, load_study_config
    from server.domains.figure import environment_figure
    from server.learners.evaluation import optimal_returns

    try:
        study = load_study_config(args.study)
    except StudyConfigError as error:  # a file that cannot be used: 2, as serve answers it
        print(f"{PROG}: {error}", file=sys.stderr)
        return 2
    if study.completion.mode == "prolific":
        from server.app.settings import SettingsError, load_settings

        try:
            currency = load_settings().prolific_currency
        except SettingsError as error:
            print(f"{PROG}: {error}", file=sys.stderr)
            return 2
        problems = prolific_problems(study, currency)
        if problems:
            print(
                f"{PROG}: {args.study}: {len(problems)} problem(s) for Prolific:", file=sys.stderr
            )
            for problem in problems:
                print(f"  {problem}", file=sys.stderr)
            return 1
    study.register_environments()
    out = args.out if args.out is not None else Path(f"{args.study.stem}-check")
    out.mkdir(parents=True, exist_ok=True)
    names = [name for domain in study.domains for name in domain.environments]
    print(f"{args.study}: no problems; {len(names)} environment(s): {', '.join(names)}")
    print_release(study)
    from server.learners.compile_notice import compile_notice

    with compile_notice(sys.stderr, PROG):
        rates = calibrate(study.learners)
    warnings = 0
    for name in names:
        env = domains.make(name)
        own = "the study's own" if name in study.environments else "built in"
        print(
            f"\n== {name} ({env.domain}, {own}): {env.width} x {env.height} cells (width x "
            f"height), {env.num_states} states, horizon {env.horizon}, {len(env.tasks)} task(s)"
        )
        print("\n".join(text_drawing(env)))
        print("tasks (number in the drawing: name, optimal return over the horizon):")
        for number, (task, best) in enumerate(zip(env.tasks, optimal_returns(env), strict=True)):
            print(f"  {number + 1}: {task.name}, {best:.1f}")
        warnings += print_traps(env)
        print(f"expected update time (size {size(env)}: states x actions x horizon x tasks):")
        for learner, rate in rates.items():
            seconds = rate * size(env)
            flag = ""
            if seconds > UPDATE_SECONDS_CAPACITY:
                warnings += 1
                flag = f"  WARNING: above the {UPDATE_SECONDS_CAPACITY:.1f} s the server can serve"
            print(f"  {learner}: {seconds:.2f} s{flag}")
        image = out / f"{name}.png"
        environment_figure(env).savefig(image, bbox_inches="tight", pad_inches=0.1)
        print(f"drawing: {image}")
    if warnings:
        print(f"\n{warnings} warning(s): see each WARNING above")
    return 0


def print_release(study: StudyConfig) -> None:
    """What the study's release (``bam-study export --format all``) will list as not answered
    by the authors: the ``[dataset]`` table's open questions."""
    from server.app.export.release import unanswered

    missing = unanswered(study.dataset)
    if missing:
        print(f"release: not answered in [dataset], and listed as such: {', '.join(missing)}")
    else:
        print("release: [dataset] answers every question the export cannot")


def print_traps(env: Environment) -> int:
    """Print each task's traps (``server.domains.reachability``); the number of warnings: a
    task with trapped reachable states, which a demonstration or an agent's try may enter and
    never leave. Trapped starts are refused when the study is loaded, unless the study
    accepts them (``max_trapped_start_share``); the paper's gravity environments start their
    simulations in every gravity, a few trapped starts included, as the authors' do."""
    from server.domains.reachability import trapped_states

    print(
        "traps (states from which the task's goal can never be reached, whatever the agent does):"
    )
    warnings = 0
    for number, task in enumerate(env.tasks):
        traps = trapped_states(env, number)
        line = f"  {number + 1}: {task.name}: {len(traps.starts)} of {traps.start_states} starts"
        if len(traps.starts):
            line += (
                f" ({traps.start_share:.1%} of the simulations' start probability, "
                f"{traps.study_start_share:.1%} of the user study's: "
                f"{traps.named(env, traps.starts)})"
            )
        line += f"; {len(traps.reachable)} of the {traps.reachable_states} reachable states"
        print(line)
        if len(traps.reachable):
            warnings += 1
            print(
                "     WARNING: a demonstration or an agent's try that enters one never reaches "
                f"the goal: {traps.named(env, traps.reachable)}"
            )
    return warnings


def texts(value: Any, path: str = "") -> Iterator[tuple[str, str]]:
    """(where, text) for every string of a study file's dumped content."""
    if isinstance(value, str):
        yield path, value
    elif isinstance(value, dict):
        for key, item in value.items():
            yield from texts(item, f"{path}.{key}" if path else str(key))
    elif isinstance(value, list | tuple):
        for index, item in enumerate(value):
            yield from texts(item, f"{path}.{index}")


def prolific_problems(study: StudyConfig, currency: str) -> list[str]:
    """What Prolific would refuse in a Prolific study that loads, or what would mislead its
    participants: no ``[prolific]`` table (``prolific create`` has nothing to make), a reward
    below Prolific's minimum hourly pay in the workspace's ``currency`` (£6 / $8 an hour for
    the estimated time; ``prolific publish`` refuses it too), and MTurk's wording in the texts
    participants read. (A maximum time below Prolific's floor is refused when the file is
    loaded: ``ProlificStudy``.)"""
    from server.commands.prolific import LEAST_HOURLY_REWARD, amount

    problems = []
    prolific = study.prolific
    if prolific is None:
        problems.append(
            "no [prolific] table: `bam-study prolific create` needs the study's name, "
            "description, places, reward, times and public_url"
        )
    else:
        hourly = prolific.reward_cents * 60 / prolific.estimated_minutes
        least = LEAST_HOURLY_REWARD[currency]
        if hourly < least:
            problems.append(
                f"prolific.reward: {amount(prolific.reward_cents, currency)} for an estimated "
                f"{prolific.estimated_minutes} minutes is {amount(hourly, currency)} an hour, "
                f"below Prolific's minimum of {amount(least, currency)} an hour (at least "
                f"{amount(-(-least * prolific.estimated_minutes // 60), currency)}); "
                "BAM_PROLIFIC_CURRENCY is the workspace's currency"
            )
    dumped = study.model_dump(mode="json", exclude=set(NOT_PARTICIPANT_TEXT))
    for where, text in texts(dumped):
        found = sorted({m.group(0) for m in MTURK_WORDING.finditer(text)})
        if found:
            problems.append(
                f"{where}: speaks of MTurk ({', '.join(repr(f) for f in found)}) to Prolific's "
                "participants: say Prolific, your Prolific ID, return the study, message the "
                "researcher through Prolific"
            )
    return problems
