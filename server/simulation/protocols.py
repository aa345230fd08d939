"""One agent's run under a simulated teacher (paper section 4): the job every experiment is
made of, and the protocol it follows.

A job is one (environment, learner, agent). Its random streams come only from (seed,
environment, learner, agent), so its numbers do not depend on which other jobs run, in which
order or where. The teacher's demonstrations and the start states they begin from come from
(seed, environment, agent) alone: every learner of the same agent index sees the same
demonstrations, so learners are compared on identical data.
"""

from __future__ import annotations

import time
import zlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from server import domains, learners
from server.domains.base import Environment
from server.learners.base import Learner
from server.learners.evaluation import optimal_returns, task_returns
from server.teacher import Teacher

CURVE_COLUMNS: tuple[str, ...] = (
    "experiment",
    "environment",
    "learner",
    "agent",
    "round",
    "normalized_return",
    "total_return",
    "optimal_return",
    "update_seconds",
)

# Last entry of a stream's SeedSequence entropy: the teacher's streams are shared by all the
# learners of an agent, the agent's own streams are not. Every entropy has the same length
# (SeedSequence treats trailing zeros as absent, so lengths must not tell streams apart).
_SHARED_STREAM = 0
_OWN_STREAM = 1


@dataclass(frozen=True)
class Job:
    """One agent of one learner in one environment, taught for ``rounds`` rounds."""

    experiment: str
    environment: str
    learner: str
    agent: int
    rounds: int
    seed: int
    settings: tuple[tuple[str, Any], ...] = ()

    @property
    def key(self) -> str:
        return f"{self.environment}/{self.learner}/{self.agent}"


@dataclass(frozen=True)
class JobResult:
    key: str
    rows: list[dict[str, Any]]
    seconds: float  # wall time of the whole job
    update_seconds: float  # of which in learner updates


def _entropy(job: Job, stream: int, learner_index: int) -> list[int]:
    return [job.seed, environment_number(job.environment), job.agent, stream, learner_index]


def environment_number(name: str) -> int:
    """A number per environment for the random streams: a built-in one's place among the
    built-in names; a study's own, one from its name alone (whatever else is registered)."""
    if name in domains.NAMES:
        return domains.NAMES.index(name)
    domains.make(name)  # an unknown name fails here, clearly
    return len(domains.NAMES) + zlib.crc32(name.encode())


def _seed(sequence: np.random.SeedSequence) -> int:
    return int(sequence.generate_state(1, np.uint64)[0])


def demonstration_streams(job: Job, env: Environment) -> tuple[Teacher, np.random.Generator]:
    """The teacher that demonstrates and the generator of the demonstrations' start states:
    from (seed, environment, agent) only, the same for every learner."""
    teacher_sequence, starts_sequence = np.random.SeedSequence(
        _entropy(job, _SHARED_STREAM, 0)
    ).spawn(2)
    return Teacher(env, seed=_seed(teacher_sequence)), np.random.default_rng(starts_sequence)


def evaluate(env: Environment, learner: Learner) -> tuple[float, float, float]:
    """(normalised return, total return, optimal total return): the exact expected total
    return over all tasks of the learner's policies under the true dynamics."""
    total = float(task_returns(env, [learner.policy(k) for k in range(len(env.tasks))]).sum())
    optimal = float(optimal_returns(env).sum())
    return total / optimal, total, optimal


def give_demonstrations(
    env: Environment, teacher: Teacher, learner: Learner, rng: np.random.Generator
) -> None:
    """One optimal demonstration per task from the task's start distribution."""
    for task in range(len(env.tasks)):
        for state, action, next_state in teacher.demonstration(task, env.sample_start(task, rng)):
            learner.record_demonstration(task, state, action, next_state)


def give_feedback(
    env: Environment, teacher: Teacher, learner: Learner, rng: np.random.Generator
) -> None:
    """One horizon-long episode per task under the agent's own policy, every step with the
    teacher's A-SABL feedback (which may be none)."""
    for task in range(len(env.tasks)):
        state = env.sample_start(task, rng)
        for _ in range(env.horizon):
            action = learner.act(task, state, rng)
            next_state = env.step(state, action, rng)
            learner.record_agent_step(
                task, state, action, next_state, teacher.feedback(task, state, action)
            )
            state = next_state


def run_agent(job: Job) -> JobResult:
    """Teach one agent for ``job.rounds`` rounds; a row per round (round 0 = before any
    data) with its exact normalised return and the time its updates took."""
    try:
        return _run_agent(job)
    except Exception as error:
        # Name the job: the error may surface in another process or on another machine.
        raise RuntimeError(f"job {job.key} failed: {type(error).__name__}: {error}") from error


def agent_streams(
    job: Job, env: Environment
) -> tuple[Learner, Teacher | None, np.random.Generator]:
    """The job's learner, the teacher that gives feedback on its episodes (feedback
    experiment only, else None) and the generator of those episodes: from (seed, environment,
    agent, learner)."""
    own_learner, own_teacher, own_episodes = np.random.SeedSequence(
        _entropy(job, _OWN_STREAM, learners.NAMES.index(job.learner))
    ).spawn(3)
    learner = learners.make(job.learner, env, seed=_seed(own_learner), **dict(job.settings))
    # The feedback teacher has its own generator: its draws depend on the learner's actions
    # and must not shift the demonstrations of later rounds.
    critic = Teacher(env, seed=_seed(own_teacher)) if job.experiment == "feedback" else None
    return learner, critic, np.random.default_rng(own_episodes)


def _run_agent(job: Job) -> JobResult:
    started = time.perf_counter()
    env = domains.make(job.environment)
    demonstrator, demonstration_rng = demonstration_streams(job, env)
    learner, critic, episode_rng = agent_streams(job, env)

    def row(round_: int, update_seconds: float) -> dict[str, Any]:
        normalized, total, optimal = evaluate(env, learner)
        return {
            "experiment": job.experiment,
            "environment": job.environment,
            "learner": job.learner,
            "agent": job.agent,
            "round": round_,
            "normalized_return": normalized,
            "total_return": total,
            "optimal_return": optimal,
            "update_seconds": update_seconds,
        }

    rows = [row(0, 0.0)]
    total_update = 0.0
    for round_ in range(1, job.rounds + 1):
        give_demonstrations(env, demonstrator, learner, demonstration_rng)
        seconds = learner.update().seconds
        if critic is not None:
            give_feedback(env, critic, learner, episode_rng)
            seconds += learner.update().seconds
        total_update += seconds
        rows.append(row(round_, seconds))
    return JobResult(job.key, rows, time.perf_counter() - started, total_update)
