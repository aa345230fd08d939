"""``bam-study teach``: simulated participants take the study over HTTP and a summary is printed."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--url", required=True, help="the study server, e.g. http://127.0.0.1:8000")
    parser.add_argument("--participants", type=int, default=4, help="how many (default 4)")
    parser.add_argument("--concurrency", type=int, default=2, help="at a time (default 2)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulated teachers")
    parser.add_argument(
        "--mistake-probability", type=float, default=0.1, help="chance of a random move (0.1)"
    )
    parser.add_argument(
        "--rounds", default="1-3", help="rounds of demonstrations per agent, e.g. 2 or 1-3"
    )
    parser.add_argument(
        "--agent-try-probability", type=float, default=0.5, help="chance of an agent try (0.5)"
    )
    parser.add_argument(
        "--think-seconds", type=float, default=0.0, help="mean pause before each move"
    )
    parser.add_argument(
        "--first-index", type=int, default=0, help="number of the first participant (new ids)"
    )
    parser.add_argument(
        "--platform",
        choices=("mturk", "prolific"),
        default="mturk",
        help="arrive as MTurk workers (the default; the study's completion mode mturk) or as "
        "Prolific participants through the server's Prolific replica (--prolific-study; "
        "one who finds the study busy with its max_concurrent_submissions tries again)",
    )
    parser.add_argument(
        "--study",
        type=Path,
        metavar="STUDY.toml",
        help="the study file the server runs, where it defines environments of its own (the "
        "simulated teachers find them by name)",
    )
    parser.add_argument(
        "--prolific-study",
        metavar="STUDY_ID",
        help="with --platform prolific: the replica's published study to take part in "
        "(signed in to the replica with BAM_ADMIN_TOKEN)",
    )


def parse_rounds(text: str) -> tuple[int, int]:
    low, _, high = text.partition("-")
    try:
        bounds = (int(low), int(high or low))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--rounds must be N or N-M, got {text!r}") from None
    if not 1 <= bounds[0] <= bounds[1]:
        raise argparse.ArgumentTypeError(f"--rounds must be 1 <= N <= M, got {text!r}")
    return bounds


def no_server_at(url: str, timeout: float = 10.0) -> str | None:
    """Why no study server answers at ``url``, or why its study cannot be taught from here
    (None: it can), asked once before any participant starts: without it each simulated
    participant retried for two minutes in silence and then failed, or took a place on
    Prolific and then failed on an environment it did not know."""
    import httpx

    from server import domains

    try:
        response = httpx.get(f"{url.rstrip('/')}/api/study", timeout=timeout)
    except httpx.InvalidURL as error:
        return f"--url {url!r} is not a URL: {error}"
    except httpx.HTTPError as error:
        return (
            f"no study server answers at {url} ({error or type(error).__name__}): start one "
            "with `bam-study serve`, or give its address with --url"
        )
    if response.status_code != 200:
        return f"{url} answered /api/study with {response.status_code}: is it a study server?"
    taught = response.json().get("environments", [])
    unknown = [name for name in taught if name not in domains.names()]
    if unknown:
        return (
            f"the study at {url} teaches environments of its own ({', '.join(unknown)}) that "
            "the simulated teachers do not know: give the server's study file with --study FILE"
        )
    return None


def run(args: argparse.Namespace) -> int:
    from server.commands.simulated import TeachingPlan, run_participants, summary_table

    try:
        low, high = parse_rounds(args.rounds)
    except argparse.ArgumentTypeError as error:
        print(f"bam-study teach: {error}", file=sys.stderr)
        return 2
    if args.participants < 1 or args.concurrency < 1:
        print(
            "bam-study teach: --participants and --concurrency must be at least 1", file=sys.stderr
        )
        return 2
    if not 0.0 <= args.mistake_probability <= 1.0 or not 0.0 <= args.agent_try_probability <= 1.0:
        print("bam-study teach: probabilities must be in [0, 1]", file=sys.stderr)
        return 2
    prolific = None
    if args.platform == "prolific":
        from server.commands.simulated import ProlificArrival

        token = os.environ.get("BAM_ADMIN_TOKEN", "")
        if not args.prolific_study or not token:
            print(
                "bam-study teach: --platform prolific needs --prolific-study STUDY_ID and "
                "BAM_ADMIN_TOKEN (the server's admin token, to take part on its replica)",
                file=sys.stderr,
            )
            return 2
        prolific = ProlificArrival(args.prolific_study, token)
    elif args.prolific_study:
        print("bam-study teach: --prolific-study goes with --platform prolific", file=sys.stderr)
        return 2
    if args.study is not None:
        from server.commands.studies import StudyEnvironmentsError, register_study

        try:
            register_study(args.study)
        except StudyEnvironmentsError as error:
            print(f"bam-study teach: {error}", file=sys.stderr)
            return 2
    unteachable = no_server_at(args.url)
    if unteachable is not None:
        print(f"bam-study teach: {unteachable}", file=sys.stderr)
        return 1
    plan = TeachingPlan(
        min_rounds=low,
        max_rounds=high,
        mistake_probability=args.mistake_probability,
        agent_try_probability=args.agent_try_probability,
        think_seconds=args.think_seconds,
    )

    def progress(participant: object) -> None:
        done = getattr(participant, "completed", False)
        error = getattr(participant, "error", None)
        index = getattr(participant, "index", "?")
        print(
            f"participant {index}: {'completed' if done else 'FAILED: ' + str(error)}", flush=True
        )

    study = run_participants(
        args.url,
        args.participants,
        args.concurrency,
        args.seed,
        plan,
        args.first_index,
        progress,
        prolific=prolific,
    )
    failed = [p for p in study.participants if not p.completed]
    print()
    print(f"participants completed  {study.completed} of {len(study.participants)}")
    print(f"learning sessions       {sum(p.sessions for p in study.participants)}")
    print(f"episodes                {sum(p.episodes for p in study.participants)}")
    print(f"events acknowledged     {study.acknowledged}")
    print(f"retried requests        {sum(p.retries for p in study.participants)}")
    print(f"wall time               {study.seconds:.1f} s")
    print()
    print(summary_table(study))
    for participant in failed:
        print(f"participant {participant.index} failed: {participant.error}", file=sys.stderr)
    return 1 if failed else 0
