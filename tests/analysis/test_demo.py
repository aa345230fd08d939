"""`bam-study demo` end to end with a few participants: a live server on a new SQLite database,
simulated participants over HTTP, the export, the analysis and Table 1; and its bad inputs."""

from __future__ import annotations

import io
import os
import shlex
import stat
import subprocess
import threading
from pathlib import Path

import pandas as pd
import pytest
from sqlalchemy import create_engine, text

from server.commands.main import main
from tests.support.demo import DemoRun, run_small_demo

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
def test_the_demo_runs_a_whole_study(
    small_demo: DemoRun, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out, stdout, stderr = small_demo.out, small_demo.stdout, small_demo.stderr
    assert small_demo.code == 0, stderr
    assert "2/2 participants 100%" in stderr  # the progress bar reached the end

    # The command printed to open the dashboard runs as printed: its program exists (the
    # virtual environment need not be active).
    (command,) = [line for line in stdout.splitlines() if line.strip().endswith(" serve")]
    words = shlex.split(command)
    program = next(word for word in words if "=" not in word)
    assert Path(program).is_absolute() and os.access(program, os.X_OK), command
    assert words[words.index(program) + 1 :] in (["serve"], ["-m", "server.commands.main", "serve"])
    # It points to the dashboard's token, in a file only its owner can read, not shows it.
    token = (out / "admin-token").read_text().strip()
    assert token and token not in stdout and token not in stderr
    assert f"BAM_ADMIN_TOKEN=$(cat {out.resolve() / 'admin-token'})" in words

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
    # The simulated participants give feedback as the paper's model of feedback does, and the
    # feedback check agrees: none is flagged for it.
    quality = pd.read_csv(out / "export" / "quality.csv")
    assert (quality["feedback_log_likelihood_ratio"] > 0).all(), quality.to_string()
    assert not quality["inconsistent_feedback"].any()
    # The participant flow: both arrived, consented, completed and were analysed.
    flow = pd.read_csv(out / "analysis" / "participant_flow.csv")
    stages = flow[flow["kind"] == "stage"].set_index("stage")["participants"].to_dict()
    assert stages == {"arrived": 2, "consented": 2, "completed": 2, "analysed": 2}
    assert (out / "analysis" / "participant_flow.png").is_file()
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


@pytest.mark.slow
def test_the_demo_gives_the_same_results_with_the_same_seed(
    small_demo: DemoRun, tmp_path: Path
) -> None:
    """Two runs with the default seed (the shared one and one of this test's own): the same
    Table 1 and the same curves, and the output names the seed and says where the figures
    come from."""
    outputs = []
    for demo in (small_demo, run_small_demo(tmp_path / "demo-2")):
        assert demo.code == 0, demo.stderr
        assert (
            "Seed 0 (`--seed` draws others): these figures come from 2 simulated participants, "
            "not from people, and differ from the paper's."
        ) in demo.stdout
        outputs.append(demo.out)
    first, second = ((out / "analysis" / "table1.md").read_text() for out in outputs)
    assert first == second
    columns = ["participant_id", "environment", "learner", "position", "seed", "episodes"]
    sessions = [pd.read_csv(out / "export" / "sessions.csv")[columns] for out in outputs]
    pd.testing.assert_frame_equal(*sessions)
    evaluations = [
        pd.read_csv(out / "export" / "evaluations.csv")[
            ["session_id", "update_index", "episodes", "actions", "normalized_return"]
        ]
        for out in outputs
    ]
    pd.testing.assert_frame_equal(*evaluations)


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
        (("--seed", "-1"), "--seed must be 0 or more, got -1"),
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


def test_the_dashboard_command_points_to_the_token_without_showing_it(tmp_path: Path) -> None:
    """The printed command reads the token from a file only its owner can read; the token is
    in no printed line, and a shell running the command's assignments gets it."""
    from server.commands.demo import TOKEN_FILE, dashboard_instructions, write_admin_token

    out = tmp_path / "my demo"  # a space: the paths must be quoted
    out.mkdir()
    token = write_admin_token(out)
    token_file = out / TOKEN_FILE
    assert len(token) >= 16
    assert stat.S_IMODE(token_file.stat().st_mode) == 0o600
    assert token_file.read_text() == token + "\n"
    with pytest.raises(FileExistsError):  # never overwritten
        write_admin_token(out)

    lines = dashboard_instructions(out)
    assert not any(token in line for line in lines)
    assert str(token_file) in "\n".join(lines)
    (command,) = [line for line in lines if line.strip().endswith(" serve")]
    assignments = command.strip().rsplit(" ", 2)[0]  # without the program and "serve"
    shown = subprocess.run(
        ["sh", "-c", f"{assignments} env"], capture_output=True, text=True, check=True
    ).stdout.splitlines()
    assert f"BAM_ADMIN_TOKEN={token}" in shown
    assert f"BAM_DATABASE_URL=sqlite:///{out / 'study.sqlite'}" in shown
    assert f"BAM_STUDY_CONFIG={out / 'study.toml'}" in shown


def test_waiting_for_the_learners_says_what_it_waits_for(tmp_path: Path) -> None:
    """After the participants, the updates still queued are explained before their progress
    bar, and the bar says what it counts."""
    from server.app.storage.db import Database
    from server.app.storage.models import LearnerUpdate, LearningSession, Participant
    from server.commands.demo import wait_for_learners
    from tests.support.databases import migrated_sqlite

    db = Database.from_url(migrated_sqlite(tmp_path / "study.sqlite"))
    with db.write() as s:
        participant = Participant(token_hash="0" * 64, platform="lab", status="submitted")
        s.add(participant)
        s.flush()
        session = LearningSession(
            participant_id=participant.id, ordinal=0, kind="study", domain="navigation",
            environment="two-rooms", learner="bam", colour_name="orange", colour_hex="#E69F00",
            seed=1,
        )  # fmt: skip
        s.add(session)
        s.flush()
        s.add(LearnerUpdate(session_id=session.id, update_index=0, episodes=0, actions=0))
        s.add(LearnerUpdate(session_id=session.id, update_index=1, episodes=1, actions=9))
    err = io.StringIO()
    waiting = threading.Thread(target=wait_for_learners, args=(db, err, tmp_path / "log", 3))
    waiting.start()
    for _ in range(600):  # until the bar is shown (a generous bound, not a timing)
        if "queued learner updates done" in err.getvalue():
            break
        waiting.join(0.1)
    with db.write() as s:
        for update in s.query(LearnerUpdate):
            update.status = "done"
    waiting.join(60)
    db.dispose()
    assert not waiting.is_alive()
    lines = err.getvalue().splitlines()
    assert lines[0] == (
        "All 3 participants have finished; the learners are still training on their last "
        "demonstrations and feedback (2 learner updates queued). The export waits for them."
    )
    assert "0/2 queued learner updates done" in lines[1]
    assert "2/2 queued learner updates done 100%" in lines[-1]
