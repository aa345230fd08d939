"""Bad arguments exit non-zero with a clear message and touch nothing."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from server.commands.main import main
from server.simulation.config import build_config, parse_learner_settings
from tests.simulation.conftest import small_args


def snapshot(folder: Path) -> dict[str, tuple[bytes, int]]:
    return {
        path.name: (path.read_bytes(), path.stat().st_mtime_ns) for path in sorted(folder.iterdir())
    }


def replace(args: list[str], option: str, *values: str) -> list[str]:
    """``args`` with ``option``'s value(s) replaced."""
    start = args.index(option) + 1
    end = start
    while end < len(args) and not args[end].startswith("--"):
        end += 1
    return [*args[:start], *values, *args[end:]]


BAD_ARGUMENTS = {
    "unknown environment": (("--environments", "wall", "moon"), "unknown environment(s): moon"),
    "unknown learner": (("--learners", "bam", "oracle"), "unknown learner(s): oracle"),
    "no agents": (("--agents", "0"), "--agents must be at least 1"),
    "no rounds": (("--rounds", "0"), "--rounds must be at least 1"),
    "negative seed": (("--seed", "-1"), "--seed must be a non-negative integer"),
    "no jobs": (("--jobs", "0"), "--jobs must be at least 1"),
    "unknown learner setting": (
        ("--learner-setting", "alternation=2"),
        "unknown learner setting(s): alternation",
    ),
    "setting without value": (("--learner-setting", "alternations"), "expects NAME=VALUE"),
    "setting of the wrong type": (
        ("--learner-setting", "alternations=two"),
        "'bam' expects an integer",
    ),
    "setting the learner rejects": (
        ("--learner-setting", "optimizer=adam"),
        "optimizer must be one of 'momentum', 'lbfgs', 'warm-lbfgs'",
    ),
}


@pytest.mark.parametrize("case", list(BAD_ARGUMENTS))
def test_bad_argument_touches_nothing(
    case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (option, *values), message = BAD_ARGUMENTS[case]
    out = tmp_path / "out"
    args = small_args(out, "feedback")
    args = replace(args, option, *values) if option in args else [*args, option, *values]
    assert main(args) != 0
    error = capsys.readouterr().err
    assert message in error
    assert "error" in error
    assert not out.exists()


def test_folder_of_another_experiment_is_refused_untouched(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    arguments = {
        "experiment": "demonstrations",
        "environments": ["wall", "doorway"],
        "learners": ["bam", "model-based", "cloning"],
        "agents": 2,
        "rounds": 2,
        "seed": 7,
        "learner_settings": {},
    }
    (out / "run.json").write_text(json.dumps({"format": 1, "arguments": arguments}))
    (out / "jobs.jsonl").write_text("")
    before = snapshot(out)
    assert main(small_args(out, "feedback", "--jobs", "1")) == 2
    error = capsys.readouterr().err
    assert "holds a different run" in error
    assert "experiment is 'demonstrations' there, 'feedback' here" in error
    assert snapshot(out) == before


def test_folder_of_the_same_experiment_with_other_arguments_is_refused(
    small_run: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    before = snapshot(small_run)
    args = replace(small_args(small_run, "feedback", "--jobs", "1"), "--agents", "3")
    assert main(args) == 2
    assert "agents is 2 there, 3 here" in capsys.readouterr().err
    args = replace(small_args(small_run, "feedback"), "--learner-setting", "alternations=3")
    assert main(args) == 2
    assert "learner_settings" in capsys.readouterr().err
    assert snapshot(small_run) == before


def test_folder_that_is_not_a_run_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "notes.txt").write_text("mine")
    before = snapshot(tmp_path)
    assert main(small_args(tmp_path, "feedback")) == 2
    assert "not a simulation output folder" in capsys.readouterr().err
    assert snapshot(tmp_path) == before
    a_file = tmp_path / "notes.txt"
    assert main(small_args(a_file, "feedback")) == 2
    assert "is not a folder" in capsys.readouterr().err
    assert snapshot(tmp_path) == before


def test_unparsable_numbers_are_refused_by_argparse(tmp_path: Path) -> None:
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exit_info:
        main(replace(small_args(out, "feedback"), "--agents", "many"))
    assert exit_info.value.code != 0
    with pytest.raises(SystemExit) as exit_info:
        main(replace(small_args(out, "feedback"), "--experiment", "imitation"))
    assert exit_info.value.code != 0
    assert not out.exists()


def test_learner_settings_go_to_the_learners_that_have_them() -> None:
    per_learner, notes = parse_learner_settings(
        ["steps=20", "cost_steps=5", "normalized_actions=false", "beta=0.5"],
        ["bam", "cloning"],
    )
    assert per_learner == {
        "bam": {"cost_steps": 5, "normalized_actions": False, "beta": 0.5},
        "cloning": {"steps": 20, "normalized_actions": False, "beta": 0.5},
    }
    assert notes == []
    # A real setting that none of this run's learners has is noted, not an error.
    per_learner, notes = parse_learner_settings(["steps=20"], ["bam", "global-cost"])
    assert per_learner == {}
    assert len(notes) == 1 and "'steps'" in notes[0]


def test_argument_order_does_not_change_the_run() -> None:
    first, _ = build_config("demonstrations", ["doorway", "wall"], None, 2, 2, 0)
    second, _ = build_config("demonstrations", ["wall", "doorway", "wall"], None, 2, 2, 0)
    assert first == second
    assert first.learners == ("bam", "model-based", "cloning")
    global_cost, _ = build_config("global-cost", None, None, 1, 1, 0)
    assert global_cost.learners == ("bam", "model-based", "global-cost")
    assert len(global_cost.environments) == 8


def test_umask_is_respected(small_run: Path) -> None:
    mask = os.umask(0)
    os.umask(mask)
    assert (small_run / "curves.csv").stat().st_mode & 0o777 == 0o666 & ~mask


def test_a_folder_another_run_is_working_in_is_refused(
    small_run: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import fcntl

    before = snapshot(small_run)
    with (small_run / ".lock").open("a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        assert main(small_args(small_run, "feedback", "--jobs", "1")) == 2
        fcntl.flock(handle, fcntl.LOCK_UN)
    assert "another run is working in" in capsys.readouterr().err
    assert snapshot(small_run) == before


def test_a_run_whose_learner_defaults_changed_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    assert (
        main(
            small_args(
                out,
                "demonstrations",
                "--agents",
                "1",
                "--rounds",
                "1",
                "--environments",
                "wall",
                "--jobs",
                "1",
            )
        )
        == 0
    )
    run = json.loads((out / "run.json").read_text(encoding="utf-8"))
    assert run["effective_settings"]["bam"]["alternations"] == 2
    assert run["effective_settings"]["bam"]["cost_learning_rate"] == 0.01
    run["effective_settings"]["bam"]["cost_learning_rate"] = 0.02  # as if the code changed
    (out / "run.json").write_text(json.dumps(run), encoding="utf-8")
    before = snapshot(out)
    assert (
        main(
            small_args(
                out,
                "demonstrations",
                "--agents",
                "1",
                "--rounds",
                "1",
                "--environments",
                "wall",
                "--jobs",
                "1",
            )
        )
        == 2
    )
    assert "bam cost_learning_rate: 0.02 there, 0.01 here" in capsys.readouterr().err
    assert snapshot(out) == before


def test_local_processes_share_the_cores_with_their_planner_threads(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Each of n busy processes gives its planner the cores the others leave (at least one),
    and a run in this process puts the count back when it ends."""
    from server.learners import planning
    from server.simulation import runner

    monkeypatch.setattr(runner, "default_workers", lambda: 4)
    assert [runner.spare_threads(n) for n in (1, 2, 3, 4, 8)] == [4, 2, 1, 1, 1]
    seen: list[int] = []
    monkeypatch.setattr(runner, "run_agent", lambda job: seen.append(planning.planner_threads()))
    before = planning.planner_threads()
    assert list(runner.LocalBackend(1).results(["a", "b"])) == [None, None]  # type: ignore[list-item]
    assert seen == [4, 4] and planning.planner_threads() == before
