"""The README runs the benchmarks as scripts (`python benchmarks/learners.py`): run that way,
the script's folder comes first on sys.path, where benchmarks/server.py would shadow the
``server`` package. Each script must import the project and parse its arguments."""

from __future__ import annotations

import re
import subprocess
import time
from pathlib import Path

import pytest

from tests.script_support import ROOT, load_script, run_script

BENCHMARKS = ROOT / "benchmarks"


def run_benchmark(script: str, *arguments: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """A benchmark script run as the README runs it, from another folder."""
    return run_script(BENCHMARKS / script, *arguments, cwd=cwd)


@pytest.mark.parametrize(
    "script", ["learners.py", "simulate.py", "server.py", "compare.py", "authors.py"]
)
def test_a_benchmark_script_starts_as_the_readme_runs_it(script: str, tmp_path: Path) -> None:
    result = run_benchmark(script, "--help", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("usage:")


@pytest.mark.parametrize(
    ("script", "arguments", "message"),
    [
        ("learners.py", ["--environments", "nowhere"], "invalid choice: 'nowhere'"),
        ("learners.py", ["--threads", "0"], "--threads must be at least 1"),
        ("compare.py", ["--against", "no-such-revision"], "'no-such-revision' is not a commit"),
        ("compare.py", ["--against", "HEAD", "--cycles", "0"], "--cycles must be at least 1"),
        ("server.py", ["--warm-alternations", "2"], "--warm-alternations needs --optimizer"),
        ("server.py", ["--servers", "0"], "--servers must be at least 1"),
        ("server.py", ["--servers", "2"], "--servers N > 1 needs --database-url postgresql"),
        ("authors.py", [], "the following arguments are required: --source"),
        ("authors.py", ["--source", "/no/such/folder"], "--source /no/such/folder is not a folder"),
        ("authors.py", ["--source", ".", "--repeats", "0"], "--repeats must be at least 1"),
        (
            "server.py",
            ["--optimizer", "warm-lbfgs", "--warm-alternations", "-1"],
            "--warm-alternations must be at least 0",
        ),
    ],
)
def test_a_bad_benchmark_argument_exits_non_zero_with_a_message(
    script: str, arguments: list[str], message: str, tmp_path: Path
) -> None:
    result = run_benchmark(script, *arguments, cwd=tmp_path)
    assert result.returncode == 2
    assert message in result.stderr
    assert "Traceback" not in result.stderr


def test_versus_times_the_same_saved_update_at_both_settings_alternately(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """``learners.py --versus``: the update at the learner's settings and the same saved state
    with the setting changed (and nothing else), one after the other, ``repeats`` times."""
    from server import domains
    from server.learners import make

    script = load_script(BENCHMARKS / "learners.py", "learners_benchmark")
    env = domains.make("wall")
    learner = make("model-based", env, seed=0)
    restored: list[dict] = []
    real_restore = script.restore

    def recording(env_, state):  # type: ignore[no-untyped-def]
        restored.append(state)
        return real_restore(env_, state)

    monkeypatch.setattr(script, "restore", recording)
    before, after = script.time_versus(env, learner, {"planner_precision": "float64"}, 2)
    assert before > 0 and after > 0
    precisions = [state["settings"]["planner_precision"] for state in restored]
    # A warm-up at the changed settings, then the two alternately.
    assert precisions == ["float64", "float32", "float64", "float32", "float64"]
    # The same saved state (the same objects) but for that one setting.
    first = restored[0]
    for state in restored:
        assert all(state[key] is first[key] for key in first if key != "settings")
        assert {k: v for k, v in state["settings"].items() if k != "planner_precision"} == {
            k: v for k, v in learner.settings.as_dict().items() if k != "planner_precision"
        }


@pytest.mark.slow
def test_compare_times_both_versions_of_the_same_update(tmp_path: Path) -> None:
    """Against HEAD itself (the same code twice): one row per environment, both versions
    timed, and the temporary worktree gone afterwards."""
    result = run_benchmark(
        "compare.py",
        *("--against", "HEAD", "--environments", "wall", "--learner", "model-based"),
        *("--rounds", "1", "--repeats", "1", "--cycles", "1"),
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    rows = [line.split() for line in result.stdout.splitlines() if line.startswith("wall ")]
    assert len(rows) == 1
    before, after = float(rows[0][1].removesuffix("ms")), float(rows[0][2].removesuffix("ms"))
    assert before > 0 and after > 0
    # The table shows whole milliseconds and the ratio of the unrounded times to two places,
    # so the ratio lies within what the rounded times allow (a 10 ms update is +-5% wide).
    ratio = float(rows[0][5])
    assert (after - 0.5) / (before + 0.5) - 0.005 <= ratio <= (after + 0.5) / (before - 0.5) + 0.005
    worktrees = subprocess.run(
        ["git", "worktree", "list"], cwd=ROOT, capture_output=True, text=True, check=True
    )
    assert "bam-compare-" not in worktrees.stdout


def test_the_server_benchmark_s_learner_settings_are_a_valid_study_file(tmp_path: Path) -> None:
    """--fast-learners, --optimizer and --warm-alternations become [learner_settings] tables
    that the study file loader accepts, each for the learners that have the setting."""
    from server.app.study_file import DEFAULT_STUDY_CONFIG, load_study_config

    module = load_script(BENCHMARKS / "server.py", "server_benchmark")
    study = tmp_path / "study.toml"
    study.write_text(
        DEFAULT_STUDY_CONFIG.read_text() + module.learner_settings_toml(True, "warm-lbfgs", 2)
    )
    config = load_study_config(study)
    assert config.learner_settings["bam"] == {
        **module.FAST_LEARNERS["bam"],
        "optimizer": "warm-lbfgs",
        "warm_alternations": 2,
    }
    assert config.learner_settings["model-based"] == {
        **module.FAST_LEARNERS["model-based"],
        "optimizer": "warm-lbfgs",
    }


BURN = """
import subprocess, sys, time
from pathlib import Path
def burn(seconds):
    began = time.process_time()
    while time.process_time() - began < seconds:
        pass
folder = Path(sys.argv[1])
if sys.argv[2] == "server":
    burn(0.3)
    subprocess.Popen([sys.executable, __file__, sys.argv[1], "update"])
else:
    burn(0.6)
    (folder / "done").write_text("")
time.sleep(120)
"""


def test_the_server_benchmark_counts_the_cores_the_server_and_its_update_processes_use(
    tmp_path: Path,
) -> None:
    """The server's own CPU time and its descendants' (the update processes) are told apart,
    and the cores line divides them by the run's length."""
    import os
    import signal
    import sys
    import time

    module = load_script(BENCHMARKS / "server.py", "server_benchmark")
    script = tmp_path / "burn.py"
    script.write_text(BURN)
    server = subprocess.Popen(
        [sys.executable, str(script), str(tmp_path), "server"], start_new_session=True
    )
    try:
        before = {name: 0.0 for name in module.cpu_by_group(server.pid, [])}
        deadline = time.monotonic() + 120
        while not (tmp_path / "done").exists():
            assert time.monotonic() < deadline, "the burning processes did not finish"
            time.sleep(0.05)
        after = module.cpu_by_group(server.pid, [])
    finally:
        os.killpg(server.pid, signal.SIGKILL)
        server.wait()
    assert 0.3 <= after["server"] < 0.6  # its own burn and its start, not its child's
    assert 0.6 <= after["update processes"] < 0.9
    assert after["Dask cluster"] == 0.0
    assert after["machine"] >= after["server"] + after["update processes"] - 0.05
    line = module.core_use_line(
        before, {**after, "simulated participants": 0.0, "machine": 1.2 * 10}, 10.0
    )
    # 10 s: the server 0.03-0.06 cores, the updates 0.06-0.09, the rest of the busy machine other.
    assert line.startswith(f"cores used (of {os.cpu_count()})")
    parts = dict(part.rsplit(" ", 1) for part in line.split(")", 1)[1].strip().split(", "))
    assert 0.03 <= float(parts["server"]) < 0.06
    assert 0.06 <= float(parts["update processes"]) < 0.09
    assert "Dask cluster" not in parts and "simulated participants" not in parts
    assert float(parts["other"]) == pytest.approx(
        1.2 - float(parts["server"]) - float(parts["update processes"]), abs=0.011
    )


def test_the_server_benchmark_reads_the_pending_updates_from_the_stop_on_while_participants_end(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The readings at the stop and a mark after it are taken then, not once the participants'
    threads have ended (those waiting for an agent end only when it is ready, which took
    longer than the mark at 200 participants)."""
    module = load_script(BENCHMARKS / "server.py", "server_benchmark")
    monkeypatch.setattr(module, "DRAINED_WITHIN_SECONDS", 0.25)
    stopped = time.perf_counter()
    # Three updates pending until 1.2 s after the stop, none after.
    monkeypatch.setattr(
        module, "pending_updates", lambda db: 3 if time.perf_counter() - stopped < 1.2 else 0
    )
    drained = module.drain_watch(None, stopped)
    time.sleep(2.0)  # the participants' threads end meanwhile
    at_stop, at_mark, drained_after = drained()
    assert (at_stop, at_mark) == (3, 3)
    assert drained_after is not None and 1.2 <= drained_after < 2.0


def test_the_server_benchmark_s_busy_share_counts_the_updates_finished_within_the_window() -> None:
    """The slots' busy share over a window: the fit and evaluation of the updates finished in
    it, over the slots' time; updates finished before or after it, or not finished, do not
    count."""
    from datetime import UTC, datetime, timedelta

    module = load_script(BENCHMARKS / "server.py", "server_benchmark")
    start = datetime(2026, 11, 27, 12, 0, tzinfo=UTC)
    at = lambda seconds: start + timedelta(seconds=seconds)  # noqa: E731
    updates = [
        (at(5), 0.5, 0.1),  # before the last minute
        (at(70), 3.0, 1.0),
        (at(100), 2.0, None),  # evaluation not recorded: the fit alone
        (at(120), 6.0, 0.0),  # at the window's end: counted
        (at(130), 9.0, 1.0),  # after it
        (None, 7.0, 1.0),  # not finished
    ]
    # Two slots for 60 s: 120 slot-seconds, 12 of them busy.
    assert module.busy_share(updates, 2, at(60), at(120)) == pytest.approx(0.1)
    # One slot over the first 120 s: 12.6 of 120.
    assert module.busy_share(updates, 1, at(0), at(120)) == pytest.approx(0.105)


def test_the_server_benchmark_says_when_the_server_s_own_work_is_not_counted() -> None:
    """On a Dask cluster the server does not time its own work per update: the capacity line
    says so instead of printing "None s"."""
    module = load_script(BENCHMARKS / "server.py", "server_benchmark")
    queue = {
        "capacity": 181,
        "update_seconds": 0.0828,
        "measured_on": "the study's learners at start",
        "slots": 2,
    }
    local = module.capacity_line({**queue, "server_seconds_per_update": 0.022})
    assert "the server's own work 0.022 s a core per update" in local
    assert local.startswith("the server's capacity: 181 participants at once (an update 0.0828 s")
    cluster = module.capacity_line({**queue, "server_seconds_per_update": None})
    assert "None" not in cluster
    assert "its own work per update not counted" in cluster and cluster.endswith("2 slot(s))")
    live = {**queue, "measured_on": "the latest 200 updates", "server_seconds_per_update": 0.05}
    assert module.capacity_line(live, " at the stop") == (
        "the server's capacity at the stop: 181 participants at once (an update 0.0828 s on "
        "the latest 200 updates, the server's own work 0.05 s a core per update, 2 slot(s))"
    )


def test_the_authors_benchmark_says_when_a_folder_holds_not_their_source(tmp_path: Path) -> None:
    result = run_benchmark("authors.py", "--source", str(tmp_path), cwd=tmp_path)
    assert result.returncode == 1
    assert "holds neither src/main/java/bam/algorithms" in result.stderr
    assert "rtloftin/discrete_bam" in result.stderr and "Traceback" not in result.stderr


def test_the_authors_benchmark_names_the_org_json_jar_it_lacks(tmp_path: Path) -> None:
    for package in ("algorithms", "domains"):
        (tmp_path / "src/main/java/bam" / package).mkdir(parents=True)
    missing = tmp_path / "no-json.jar"
    result = run_benchmark(
        "authors.py", "--source", str(tmp_path), "--json-jar", str(missing), cwd=tmp_path
    )
    assert result.returncode == 1
    assert f"{missing} not found: give an org.json jar with --json-jar" in result.stderr
    assert "Traceback" not in result.stderr


def test_the_authors_benchmark_reads_their_enums_without_get_enum() -> None:
    """Their loaders read enums with org.json's ``getEnum``, which Debian's jar lacks: the
    rewrite reads the same name from the same array, and leaves other lines alone."""
    module = load_script(BENCHMARKS / "authors.py", "authors_benchmark")
    java = (
        "colors[row][column] = columns.getEnum(Colors.class, column);\n"
        "gravity[color] = mapping.getEnum(Gravity.class, color);\n"
        'int depth = json.getInt("depth");\n'
    )
    assert module.without_get_enum(java) == (
        "colors[row][column] = Enum.valueOf(Colors.class, columns.getString(column));\n"
        "gravity[color] = Enum.valueOf(Gravity.class, mapping.getString(color));\n"
        'int depth = json.getInt("depth");\n'
    )


def test_the_authors_benchmark_sets_their_median_beside_ours_and_judges_round_10() -> None:
    module = load_script(BENCHMARKS / "authors.py", "authors_benchmark")
    # Two agents a learner, the second 100 ms slower, each update 1 ms slower a round.
    lines = [
        f"wall {learner} {agent} {round_} {base + 100 * agent + round_}"
        for learner, base in (("bam", 300.0), ("model-based", 150.0))
        for agent in (0, 1)
        for round_ in range(1, 11)
    ]
    theirs = module.parse_their_times("\n".join(lines) + "\n")
    assert theirs[("wall", "bam", 10)] == [310.0, 410.0]
    ours = module.parse_our_times(
        "planner threads: 1, clock: wall\n"
        "environment   learner  upd@1 med/p95 ms ...\n"
        "wall          bam                 18/86               14/15               15/15  "
        "0.02 0.07 3.3 6.6\n"
        "wall          model-based          8/15                5/5                 10/12  "
        "0.02 0.07 3.3 5.8\n"
    )
    assert ours[("wall", "bam", 1)] == 18.0 and ours[("wall", "model-based", 10)] == 10.0
    text, short = module.table(theirs, ours)
    # BAM: median of 310 and 410 is 360, over 15 ms: 24 times; model-based 210 / 10: 21.
    bam = next(line for line in text.splitlines() if line.startswith("wall          bam"))
    assert bam.split()[-2:] == ["360/15", "24"]
    assert short == []
    slower = {**ours, ("wall", "model-based", 10): 20.0}
    assert module.table(theirs, slower)[1] == ["wall model-based (10 times)"]


def test_the_authors_benchmark_pins_both_sides_to_a_core_it_may_use(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """A container's cpuset may leave out the host's last core: taskset onto it would fail."""
    module = load_script(BENCHMARKS / "authors.py", "authors_benchmark")
    monkeypatch.setattr(module.shutil, "which", lambda name: f"/usr/bin/{name}")
    monkeypatch.setattr(module.os, "sched_getaffinity", lambda pid: {2, 5}, raising=False)
    monkeypatch.setattr(module.os, "cpu_count", lambda: 16)
    assert module.pinned(["java", "X"]) == ["/usr/bin/taskset", "-c", "5", "java", "X"]
    monkeypatch.setattr(module.shutil, "which", lambda name: None)
    assert module.pinned(["java", "X"]) == ["java", "X"]


def test_the_authors_harness_runs_the_environments_the_benchmark_names() -> None:
    """The Java harness maps each of our environment names to one of their layouts."""
    module = load_script(BENCHMARKS / "authors.py", "authors_benchmark")
    harness = module.HARNESS.read_text(encoding="utf-8")
    assert tuple(re.findall(r'ENVIRONMENTS\.put\("([a-z-]+)"', harness)) == module.ENVIRONMENTS
