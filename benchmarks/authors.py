"""The paper authors' implementation beside ours: BAM's and model-based IRL's update after 1, 5
and 10 rounds of demonstrations, timed in their Java implementation and in ours on the same
machine and core, one thread each, and how many times faster ours is.

    python benchmarks/authors.py --source PATH [--environments wall flip] [--repeats 3]

PATH is a copy of the authors' repository (GitHub ``rtloftin/discrete_bam``): a working tree or
a bare git directory. Their learners and environments (``src/main/java/bam/algorithms`` and
``bam/domains``) are compiled with ``benchmarks/authors/UpdateTimes.java``, which builds BAM and
model-based IRL as their demonstrations experiment does (``SimulationMain.java``), feeds them
their expert's goal-terminated demonstrations with the final no-op, and times every update
(``Agent.integrate``). Our side is ``benchmarks/learners.py --threads 1`` on the same
environments. Both run on one core, the last this process may use, with ``taskset`` where it
exists, and theirs told it has one processor.

Needs a JDK (``javac``, ``java``) and an ``org.json`` jar: by default Debian's
``libandroid-json-java`` (``/usr/share/java/com.android.json.jar``). That one lacks
``JSONArray.getEnum``; the four calls of it, in their loaders of saved environments (not run
here), are rewritten to ``Enum.valueOf`` in the copy compiled. Nothing else of theirs changes.

Target (2-core machine, update after 10 rounds, median): ours at least 20 times faster than
theirs in every environment.
"""

from __future__ import annotations

import argparse
import io
import os
import re
import shutil
import statistics
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

# Run as a script, this folder comes first on sys.path, and benchmarks/server.py would
# shadow the ``server`` package.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

from server import domains

HERE = Path(__file__).resolve().parent
HARNESS = HERE / "authors" / "UpdateTimes.java"
ENVIRONMENTS = tuple(domains.ENVIRONMENTS)  # the paper's eight, each a layout of theirs
LEARNERS = ("bam", "model-based")
CHECKPOINTS = (1, 5, 10)
PACKAGES = ("src/main/java/bam/algorithms", "src/main/java/bam/domains")
JSON_JAR = Path("/usr/share/java/com.android.json.jar")
TARGET = 20.0
GET_ENUM = re.compile(r"(\w+)\.getEnum\((\w+)\.class, (\w+)\)")


class SourceError(Exception):
    """The authors' source cannot be found or compiled; the message says why."""


def without_get_enum(java: str) -> str:
    """``array.getEnum(Type.class, i)`` as ``Enum.valueOf(Type.class, array.getString(i))``:
    the same value for org.json's arrays of enum names, in a jar that lacks ``getEnum``."""
    return GET_ENUM.sub(r"Enum.valueOf(\2.class, \1.getString(\3))", java)


def copy_source(source: Path, into: Path) -> None:
    """The authors' learner and environment packages from a working tree or a bare git
    directory, copied under ``into`` with ``getEnum`` rewritten."""
    if all((source / package).is_dir() for package in PACKAGES):
        for package in PACKAGES:
            shutil.copytree(source / package, into / package)
    else:
        archive = subprocess.run(
            ["git", f"--git-dir={source}", "archive", "HEAD", *PACKAGES],
            capture_output=True,
        )
        if archive.returncode != 0:
            raise SourceError(
                f"{source} holds neither {' nor '.join(PACKAGES)} nor a git history with "
                "them: give a copy of the authors' repository (GitHub rtloftin/discrete_bam)"
            )
        with tarfile.open(fileobj=io.BytesIO(archive.stdout)) as tar:
            tar.extractall(into, filter="data")
    for path in into.rglob("*.java"):
        text = path.read_text(encoding="utf-8")
        if GET_ENUM.search(text):
            path.write_text(without_get_enum(text), encoding="utf-8")


def pinned(command: list[str]) -> list[str]:
    """The command on the last core this process may run on (its CPU affinity: a container's
    cpuset narrows it, and ``os.cpu_count()`` counts the host's), where ``taskset`` exists."""
    taskset = shutil.which("taskset")
    if taskset is None or not hasattr(os, "sched_getaffinity"):
        return command
    return [taskset, "-c", str(max(os.sched_getaffinity(0))), *command]


def their_times(
    source: Path, json_jar: Path, environments: list[str], repeats: int
) -> dict[tuple[str, str, int], list[float]]:
    """Their update times in ms, by (environment, learner, round), one per agent."""
    with tempfile.TemporaryDirectory(prefix="bam-authors-") as folder:
        root = Path(folder)
        copy_source(source, root)
        for tool in ("javac", "java"):
            if shutil.which(tool) is None:
                raise SourceError(f"{tool} not found: install a JDK (Debian: default-jdk-headless)")
        if not json_jar.is_file():
            raise SourceError(
                f"{json_jar} not found: give an org.json jar with --json-jar "
                "(Debian: apt-get install libandroid-json-java)"
            )
        classes = root / "classes"
        sources = [str(p) for p in sorted(root.rglob("*.java"))]
        javac = ["javac", "-nowarn", "-encoding", "UTF-8", "-cp", str(json_jar)]
        compiled = subprocess.run(
            [*javac, "-d", str(classes), *sources, str(HARNESS)],
            capture_output=True,
            text=True,
        )
        if compiled.returncode != 0:
            raise SourceError(f"their source did not compile:\n{compiled.stderr.strip()}")
        run = subprocess.run(
            pinned(
                [
                    "java",
                    "-XX:ActiveProcessorCount=1",
                    "-cp",
                    os.pathsep.join([str(classes), str(json_jar)]),
                    "UpdateTimes",
                    str(max(CHECKPOINTS)),
                    str(repeats),
                    *environments,
                ]
            ),
            capture_output=True,
            text=True,
        )
        if run.returncode != 0:
            raise SourceError(f"their learners failed:\n{run.stderr.strip()}")
    return parse_their_times(run.stdout)


def parse_their_times(output: str) -> dict[tuple[str, str, int], list[float]]:
    """``environment learner agent round ms`` lines, by (environment, learner, round)."""
    times: dict[tuple[str, str, int], list[float]] = {}
    for line in output.splitlines():
        environment, learner, _agent, round_, milliseconds = line.split()
        times.setdefault((environment, learner, int(round_)), []).append(float(milliseconds))
    return times


def our_times(environments: list[str], repeats: int) -> dict[tuple[str, str, int], float]:
    """Our median update times in ms, from ``learners.py --threads 1``'s table."""
    run = subprocess.run(
        pinned(
            [
                sys.executable,
                str(HERE / "learners.py"),
                "--threads",
                "1",
                "--repeats",
                str(repeats),
                "--learners",
                *LEARNERS,
                "--environments",
                *environments,
            ]
        ),
        capture_output=True,
        text=True,
    )
    if run.returncode != 0:
        raise SourceError(f"our learners benchmark failed:\n{run.stderr.strip()}")
    return parse_our_times(run.stdout)


def parse_our_times(table: str) -> dict[tuple[str, str, int], float]:
    """The medians of learners.py's ``upd@N med/p95`` cells, by (environment, learner, round)."""
    times = {}
    for line in table.splitlines():
        fields = line.split()
        if len(fields) > 2 and fields[0] in ENVIRONMENTS and fields[1] in LEARNERS:
            for round_, cell in zip(CHECKPOINTS, fields[2:], strict=False):
                times[(fields[0], fields[1], round_)] = float(cell.split("/")[0])
    return times


def table(
    theirs: dict[tuple[str, str, int], list[float]], ours: dict[tuple[str, str, int], float]
) -> tuple[str, list[str]]:
    """The side-by-side table, and the environments and learners under the target."""
    header = f"{'environment':13s} {'learner':12s}" + "".join(
        f" {'upd@' + str(r) + ' theirs/ours ms':>22s} {'x':>5s}" for r in CHECKPOINTS
    )
    lines = [header, "-" * len(header)]
    short = []
    for environment, learner in dict.fromkeys((e, lr) for e, lr, _ in theirs):
        cells = []
        for round_ in CHECKPOINTS:
            their = statistics.median(theirs[(environment, learner, round_)])
            our = ours[(environment, learner, round_)]
            ratio = their / max(our, 0.5)
            cells.append(f" {f'{their:.0f}/{our:.0f}':>22s} {ratio:5.0f}")
            if round_ == max(CHECKPOINTS) and ratio < TARGET:
                short.append(f"{environment} {learner} ({ratio:.0f} times)")
        lines.append(f"{environment:13s} {learner:12s}" + "".join(cells))
    return "\n".join(lines), short


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--source",
        type=Path,
        required=True,
        help="the authors' repository (rtloftin/discrete_bam): a working tree or bare git dir",
    )
    parser.add_argument("--environments", nargs="+", choices=ENVIRONMENTS, default=ENVIRONMENTS)
    parser.add_argument(
        "--repeats", type=int, default=3, help="their agents per learner; our timed updates"
    )
    parser.add_argument(
        "--json-jar", type=Path, default=JSON_JAR, help=f"an org.json jar (default: {JSON_JAR})"
    )
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    if not args.source.is_dir():
        parser.error(f"--source {args.source} is not a folder")
    environments = list(args.environments)
    try:
        theirs = their_times(args.source.resolve(), args.json_jar, environments, args.repeats)
        ours = our_times(environments, args.repeats)
    except SourceError as error:
        print(f"authors.py: {error}", file=sys.stderr)
        return 1
    text, short = table(theirs, ours)
    print(f"one core each; theirs: median of {args.repeats} agents; ours: learners.py --threads 1")
    print(text)
    verdict = "met" if not short else "not met in " + ", ".join(short)
    rounds = max(CHECKPOINTS)
    print(f"\ntarget: ours at least {TARGET:.0f} times faster after {rounds} rounds: {verdict}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
