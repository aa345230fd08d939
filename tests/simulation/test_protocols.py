"""One agent's run: the protocols of the three experiments, their random streams, and the
progress bar."""

from __future__ import annotations

import io
from typing import Any

import numpy as np
import pytest

from server import domains, learners
from server.learners.base import Learner
from server.simulation import protocols
from server.simulation.config import RunConfig
from server.simulation.outputs import report_rounds, summarize
from server.simulation.progress import Progress, format_duration
from server.simulation.protocols import Job, run_agent
from server.simulation.runner import plan_jobs

FAST = {"alternations": 2, "cost_steps": 5, "dynamics_steps": 5, "steps": 20}


def job(learner: str = "bam", experiment: str = "demonstrations", **changes: Any) -> Job:
    defaults = learners.learner_class(learner).default_settings
    settings = tuple((name, value) for name, value in FAST.items() if name in defaults)
    values: dict[str, Any] = {
        "experiment": experiment,
        "environment": "wall",
        "learner": learner,
        "agent": 0,
        "rounds": 2,
        "seed": 3,
        "settings": settings,
    }
    values.update(changes)
    return Job(**values)


@pytest.fixture
def taught(monkeypatch: pytest.MonkeyPatch) -> list[Learner]:
    """The learners that ``run_agent`` creates, kept for inspection."""
    made: list[Learner] = []
    real_make = learners.make

    def make(*args: Any, **kwargs: Any) -> Learner:
        learner = real_make(*args, **kwargs)
        made.append(learner)
        return learner

    monkeypatch.setattr(protocols.learners, "make", make)
    return made


def numbers(rows: list[dict[str, Any]]) -> list[tuple[Any, ...]]:
    return [
        (r["round"], r["normalized_return"], r["total_return"], r["optimal_return"]) for r in rows
    ]


def test_every_learner_of_an_agent_sees_the_same_demonstrations(taught: list[Learner]) -> None:
    for name in ("bam", "model-based", "cloning", "global-cost"):
        run_agent(job(name, experiment="global-cost"))
    demonstrations = [learner.data.demonstrations for learner in taught]
    assert len(demonstrations[0]) > 0
    for other in demonstrations[1:]:
        np.testing.assert_array_equal(other, demonstrations[0])
    run_agent(job("bam", agent=1))
    assert not np.array_equal(taught[-1].data.demonstrations, demonstrations[0])


def test_demonstration_protocol(taught: list[Learner]) -> None:
    result = run_agent(job("bam"))
    learner = taught[0]
    env = domains.make("wall")
    assert learner.updates == 2
    assert len(learner.data.agent_steps) == 0
    # One demonstration per task per round: each ends with one optimal action at the goal.
    at_goal = [env.is_goal(task, state) for task, state, _, _ in learner.data.demonstrations]
    assert sum(at_goal) == 2 * len(env.tasks)
    assert [row["round"] for row in result.rows] == [0, 1, 2]
    assert result.update_seconds == pytest.approx(sum(r["update_seconds"] for r in result.rows))
    assert 0 < result.update_seconds <= result.seconds


def test_feedback_protocol(taught: list[Learner]) -> None:
    run_agent(job("model-based", experiment="feedback"))
    learner = taught[0]
    env = domains.make("wall")
    assert learner.updates == 4  # after the demonstrations and after the episodes, each round
    steps = learner.data.agent_steps
    assert len(steps) == 2 * len(env.tasks) * env.horizon
    assert set(np.unique(steps[:, 4])) <= {-1, 0, 1}
    assert np.any(steps[:, 4] != 0)
    # Each task's episode is one horizon-long trajectory: every step starts where the last ended.
    for episode in steps.reshape(-1, env.horizon, 5):
        assert len(set(episode[:, 0])) == 1
        np.testing.assert_array_equal(episode[1:, 1], episode[:-1, 3])


def test_feedback_does_not_shift_the_demonstrations(taught: list[Learner]) -> None:
    run_agent(job("bam", experiment="demonstrations"))
    run_agent(job("bam", experiment="feedback"))
    np.testing.assert_array_equal(taught[0].data.demonstrations, taught[1].data.demonstrations)


def test_a_job_is_reproducible_and_depends_on_its_seed() -> None:
    first = run_agent(job("cloning"))
    again = run_agent(job("cloning"))
    assert numbers(first.rows) == numbers(again.rows)
    other = run_agent(job("cloning", seed=4))
    assert numbers(other.rows)[1:] != numbers(first.rows)[1:]


def test_round_zero_is_the_untrained_learner() -> None:
    env = domains.make("wall")
    result = run_agent(job("bam", rounds=1))
    untrained = learners.make("bam", env)
    normalized, total, optimal = protocols.evaluate(env, untrained)
    assert result.rows[0]["normalized_return"] == pytest.approx(normalized)
    assert result.rows[0]["update_seconds"] == 0.0
    assert total <= optimal


def test_a_failing_job_names_itself() -> None:
    with pytest.raises(RuntimeError, match="job wall/bam/0 failed"):
        run_agent(job("bam", settings=(("alternations", 1), ("cost_steps", "many"))))


def test_plan_is_agent_major_and_complete() -> None:
    config = RunConfig("demonstrations", ("wall", "doorway"), ("bam", "cloning"), 3, 2, 0)
    plan = plan_jobs(config)
    assert len(plan) == len({j.key for j in plan}) == 3 * 2 * 2
    assert [j.agent for j in plan[:4]] == [0, 0, 0, 0]
    assert {j.environment for j in plan[:4]} == {"wall", "doorway"}


def test_summary_of_one_agent_has_no_standard_error() -> None:
    config = RunConfig("demonstrations", ("wall",), ("bam",), 1, 1, 0)
    rows = [
        {
            "environment": "wall",
            "learner": "bam",
            "agent": 0,
            "round": r,
            "normalized_return": 0.5,
            "total_return": 1.0,
            "optimal_return": 2.0,
            "update_seconds": 0.0,
        }
        for r in (0, 1)
    ]
    summary = summarize(config, rows)
    assert [row.agents for row in summary] == [1, 1]
    assert all(np.isnan(row.se_normalized_return) for row in summary)
    assert report_rounds(10) == [0, 1, 2, 5, 10]
    assert report_rounds(1) == [0, 1]


def test_progress_estimates_time_left_and_stays_quiet_in_logs() -> None:
    stream = io.StringIO()
    progress = Progress(total=100, done=20, stream=stream)
    progress.start()
    assert progress.seconds_left() is None
    progress.started -= 10.0  # ten seconds for the first 20 jobs of this session
    for _ in range(20):
        progress.advance()
    left = progress.seconds_left()
    assert left is not None and left == pytest.approx(30.0, rel=0.05)
    for _ in range(60):
        progress.advance()
    progress.finish()
    lines = stream.getvalue().splitlines()
    assert lines[0] == "resuming: 20 of 100 jobs already done"
    assert 5 <= len(lines) <= 12  # a line per tenth, not per job
    assert lines[-1].startswith("[" + "#" * 30 + "] 100/100 jobs 100%")
    assert lines[-1].endswith("done")
    assert format_duration(75) == "1m15s" and format_duration(7300) == "2h01m"
