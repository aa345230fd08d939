"""`bam-study demo` end to end with a few participants: a live server on a new SQLite database,
simulated participants over HTTP, the export, the analysis and Table 1; and its bad inputs."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
from sqlalchemy import create_engine, text

from server.cli import main

LEARNERS = {"bam": "BAM", "model-based": "Model-Based IRL", "cloning": "Behavioral Cloning"}
ENVIRONMENTS = {
    "two-rooms": "Two Rooms",
    "doorway": "Doorway",
    "two-fields": "Two Fields",
    "three-fields": "Three Fields",
}


def run(capsys: pytest.CaptureFixture[str], *args: str | Path) -> tuple[int, str, str]:
    try:
        code = main([str(a) for a in args])
    except SystemExit as exit:  # argparse refused the arguments
        code = int(exit.code or 0)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


@pytest.mark.slow
def test_the_demo_runs_a_whole_study(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "demo"
    code, stdout, stderr = run(
        capsys,
        "demo",
        "--out", out,
        "--participants", 2,
        "--concurrency", 2,
        "--rounds", 1,
        "--workers", 2,
    )  # fmt: skip
    assert code == 0, stderr
    assert "2/2 participants 100%" in stderr  # the progress bar reached the end

    # Table 1 is printed, as written in the analysis folder, with every cell's learner.
    table = (out / "analysis" / "table1.md").read_text()
    assert table.strip() in stdout
    for name in (*ENVIRONMENTS.values(), *LEARNERS.values()):
        assert name in table

    # The database holds the whole study: both participants submitted, every agent finished
    # and every learner update done.
    engine = create_engine(f"sqlite:///{out / 'study.sqlite'}")
    with engine.connect() as connection:
        statuses = connection.execute(text("SELECT status FROM participants")).scalars().all()
        updates = dict(
            connection.execute(
                text("SELECT status, count(*) FROM learner_updates GROUP BY status")
            ).all()
        )
    engine.dispose()
    assert statuses == ["submitted", "submitted"]
    assert set(updates) == {"done"}

    # The export and the analysis agree with it: 2 participants x 6 agents, one evaluation per
    # update (update 0 is the untrained learner), and the one-per-domain balance.
    sessions = pd.read_csv(out / "export" / "sessions.csv")
    evaluations = pd.read_csv(out / "export" / "evaluations.csv")
    assert len(sessions) == 12 and sessions["completed"].all()
    assert sorted(sessions["domain"].value_counts().tolist()) == [6, 6]
    for session_id, group in evaluations.groupby("session_id"):
        episodes = int(sessions.set_index("session_id").at[session_id, "episodes"])
        assert list(group["update_index"]) == list(range(episodes + 1))
    summary = pd.read_csv(out / "analysis" / "sessions_summary.csv")
    assert len(summary) == 12
    assert set(zip(summary["environment"], summary["learner"], strict=True)) == {
        (environment, learner) for environment in ENVIRONMENTS for learner in LEARNERS
    }

    # The analysis can read the demo's database directly (read-only) with the same result.
    code, _, stderr = run(
        capsys, "analyze", "--database-url", f"sqlite:///{out / 'study.sqlite'}",
        "--out", tmp_path / "again",
    )  # fmt: skip
    assert code == 0, stderr
    assert (tmp_path / "again" / "table1.md").read_text() == table


def test_the_demo_needs_a_new_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "used"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    code, _, stderr = run(capsys, "demo", "--out", out, "--participants", 1)
    assert code == 2
    assert f"--out {out} is not empty" in stderr
    assert [p.name for p in out.iterdir()] == ["notes.txt"]
    assert (out / "notes.txt").read_text() == "keep me"


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("--participants", "0"), "--participants must be at least 1, got 0"),
        (("--concurrency", "0"), "--concurrency must be at least 1, got 0"),
        (("--workers", "-1"), "--workers must be 0 (one per core) or more, got -1"),
        (("--rounds", "3-1"), "--rounds must be 1 <= N <= M"),
    ],
)
def test_bad_demo_arguments(
    args: tuple[str, ...], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "demo"
    code, _, stderr = run(capsys, "demo", "--out", out, *args)
    assert code == 2
    assert message in stderr
    assert not out.exists()
