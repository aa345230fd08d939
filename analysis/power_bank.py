"""The bank of simulated sessions behind ``bam-study power``.

A *simulated participant* of a domain is a teacher whose skill and feedback are drawn once
(``Traits``) and kept for every agent they teach, as a person's are: how often a demonstrated
move is a random one, how decisive their + and - are (A-SABL's alpha, the paper's model of
feedback, section 3), how many rounds they teach each agent and how often they let the agent
try. They teach one agent of each of the study's learners in each environment of their domain,
as the study's participants do: each round, every task gets a demonstration (moves only, then
the STAY the study page appends) from a start of the study's, an update and an evaluation; then,
at the participant's rate, an agent try of up to the horizon's steps with their feedback, an
update and an evaluation. A session's outcome is its curve: the episodes and actions taught
and the exact normalised return after every update (``evaluate``, as the simulation reports).

Simulating real learners is the costly part, so each session is simulated once: the bank holds
``participants`` simulated participants per domain, their sessions journalled one line each
in the output folder (``power_bank.jsonl``); a run with the same arguments reuses them and
simulates only what is missing. The studies are then resampled from the bank
(``analysis.power``).

Every random stream comes from (seed, domain, participant, environment, learner) alone: a
participant's traits from (seed, domain, participant), the demonstrations and the choice of
agent tries from (seed, domain, participant, environment), shared by the learners of a block,
as in the paper's simulations; the agent's own draws and the feedback on them from the session.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import signal
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from server import domains, learners
from server.domains.base import STAY
from server.domains.spec import EnvironmentSpec
from server.simulation.config import ConfigError
from server.simulation.protocols import environment_number, evaluate
from server.teacher import Teacher

BANK_FILE = "power_bank.json"
JOURNAL_FILE = "power_bank.jsonl"
FORMAT_VERSION = 1
# The same length for every stream's entropy (SeedSequence drops trailing zeros).
_TRAITS, _BLOCK, _SESSION = 1, 2, 3
# Starts drawn at most to find one off the task's goal (the study page redraws too).
START_DRAWS = 5


@dataclass(frozen=True)
class Population:
    """How the simulated participants differ from one another (``Traits`` is one draw).

    - ``mistake_mean``, ``mistake_concentration``: the chance that a demonstrated move is a
      random one follows a Beta distribution with this mean and a + b (0.1 and 10: most
      people err on 0 to 25% of their moves);
    - ``alpha_median``, ``alpha_spread``: A-SABL's alpha is log-normal, with the paper's
      alpha (1) as its median and this standard deviation of its logarithm (1: from about a
      seventh to seven times the paper's, 95% of the participants);
    - ``rounds``: rounds of teaching per agent, uniform over this range (inclusive);
    - ``agent_try``: the chance of an agent try after each demonstration, uniform over this
      range per participant.
    """

    mistake_mean: float = 0.1
    mistake_concentration: float = 10.0
    alpha_median: float = 1.0
    alpha_spread: float = 1.0
    rounds: tuple[int, int] = (3, 5)
    agent_try: tuple[float, float] = (0.25, 0.75)

    def __post_init__(self) -> None:
        low, high = self.rounds
        if not 1 <= low <= high:
            raise ConfigError(f"--rounds: give N or N-M with 1 <= N <= M, got {low}-{high}")
        if not 0 < self.mistake_mean < 1 or self.mistake_concentration <= 0:
            raise ConfigError("the mistake probability's mean must be in (0, 1)")
        if self.alpha_median <= 0 or self.alpha_spread < 0:
            raise ConfigError("alpha's median must be above 0 and its spread at least 0")
        if not 0 <= self.agent_try[0] <= self.agent_try[1] <= 1:
            raise ConfigError("the agent-try range must lie in [0, 1]")

    def to_json(self) -> dict[str, Any]:
        values = asdict(self)
        values["rounds"] = list(self.rounds)
        values["agent_try"] = list(self.agent_try)
        return values


@dataclass(frozen=True)
class Traits:
    """One simulated participant's skill, feedback and effort, shared by all their agents."""

    mistake_probability: float
    feedback_alpha: float
    rounds: int
    agent_try_probability: float


def _sequence(seed: int, domain: int, participant: int, stream: int, *rest: int) -> Any:
    words = [seed, domain, participant, stream, *rest]
    return np.random.SeedSequence(words + [0] * (6 - len(words)))


def draw_traits(population: Population, seed: int, domain: int, participant: int) -> Traits:
    rng = np.random.default_rng(_sequence(seed, domain, participant, _TRAITS))
    a = population.mistake_mean * population.mistake_concentration
    b = (1 - population.mistake_mean) * population.mistake_concentration
    low, high = population.rounds
    return Traits(
        mistake_probability=float(rng.beta(a, b)),
        feedback_alpha=float(
            population.alpha_median * np.exp(population.alpha_spread * rng.normal())
        ),
        rounds=int(rng.integers(low, high + 1)),
        agent_try_probability=float(rng.uniform(*population.agent_try)),
    )


@dataclass(frozen=True)
class SessionJob:
    """One simulated participant's session: one agent of ``learner`` in ``environment``."""

    domain: str
    domain_index: int
    participant: int
    environment: str
    learner: str
    seed: int
    traits: Traits
    settings: tuple[tuple[str, Any], ...] = ()

    @property
    def key(self) -> str:
        return f"{self.domain}/{self.participant}/{self.environment}/{self.learner}"


def _integer_seed(sequence: np.random.SeedSequence) -> int:
    return int(sequence.generate_state(1, np.uint64)[0])


def simulate_session(job: SessionJob) -> dict[str, Any]:
    """The session's row: its key, fields and curve (``[episodes, actions, normalised
    return]`` before any teaching and after every update)."""
    env = domains.make(job.environment)
    number = environment_number(job.environment)
    shared = _sequence(job.seed, job.domain_index, job.participant, _BLOCK, number)
    demonstrator_seed, starts, choices = shared.spawn(3)
    own = _sequence(
        job.seed,
        job.domain_index,
        job.participant,
        _SESSION,
        number,
        learners.NAMES.index(job.learner),
    )
    learner_seed, critic_seed, episodes_seed = own.spawn(3)
    traits = job.traits
    demonstrator = Teacher(
        env,
        seed=_integer_seed(demonstrator_seed),
        mistake_probability=traits.mistake_probability,
        style="person",
    )
    critic = Teacher(env, seed=_integer_seed(critic_seed), alpha=traits.feedback_alpha)
    start_rng, choice_rng = np.random.default_rng(starts), np.random.default_rng(choices)
    episode_rng = np.random.default_rng(episodes_seed)
    learner = learners.make(
        job.learner, env, seed=_integer_seed(learner_seed), **dict(job.settings)
    )
    episodes = actions = 0
    curve = [[0, 0, evaluate(env, learner)[0]]]
    for _ in range(traits.rounds):
        for task in range(len(env.tasks)):
            start = env.sample_start(task, start_rng, study=True)
            for _ in range(START_DRAWS - 1):
                if not env.is_goal(task, start):
                    break
                start = env.sample_start(task, start_rng, study=True)
            # Drawn for every demonstration, whatever the learner does: the same tries in
            # every session of the block.
            tries = bool(choice_rng.random() < traits.agent_try_probability)
            if env.is_goal(task, start):
                continue  # nothing to demonstrate from there
            for state, action, next_state in demonstrator.demonstration(task, start):
                learner.record_demonstration(task, state, action, next_state)
                actions += action != STAY  # the appended STAY is the page's, not a key press
            episodes += 1
            learner.update()
            curve.append([episodes, actions, evaluate(env, learner)[0]])
            if not tries:
                continue
            state = env.sample_start(task, episode_rng, study=True)
            for _ in range(env.horizon):
                if env.is_goal(task, state):
                    break
                action = learner.act(task, state, episode_rng)
                next_state = env.step(state, action, episode_rng)
                learner.record_agent_step(
                    task, state, action, next_state, critic.feedback(task, state, action)
                )
                actions += 1
                state = next_state
            episodes += 1
            learner.update()
            curve.append([episodes, actions, evaluate(env, learner)[0]])
    return {
        "key": job.key,
        "domain": job.domain,
        "participant": job.participant,
        "environment": job.environment,
        "learner": job.learner,
        **asdict(traits),
        "curve": curve,
    }


@dataclass(frozen=True)
class BankPlan:
    """What a bank is made of: the study's domains (name -> environments), the learners
    simulated, the settings of every learner of the study, the participants simulated per
    domain, the population and the seed."""

    domains: tuple[tuple[str, tuple[str, ...]], ...]
    learners: tuple[str, ...]
    participants: int
    seed: int
    population: Population = field(default_factory=Population)
    settings: tuple[tuple[str, tuple[tuple[str, Any], ...]], ...] = ()

    def settings_of(self, learner: str) -> tuple[tuple[str, Any], ...]:
        return dict(self.settings).get(learner, ())

    def jobs(self) -> list[SessionJob]:
        """Every session, participant-major so that any prefix mixes domains and learners."""
        return [
            SessionJob(
                domain,
                index,
                participant,
                environment,
                learner,
                self.seed,
                draw_traits(self.population, self.seed, index, participant),
                self.settings_of(learner),
            )
            for participant in range(self.participants)
            for index, (domain, environments) in enumerate(self.domains)
            for environment in environments
            for learner in self.learners
        ]

    def identity(self) -> dict[str, Any]:
        """What every journalled session depends on: not the learners compared nor how many
        participants there are, so that a bank grows and serves any pair of the study's
        learners (``settings`` names every learner of the study)."""
        return {
            "format": FORMAT_VERSION,
            "seed": self.seed,
            "domains": {name: list(envs) for name, envs in self.domains},
            "population": self.population.to_json(),
            "effective_settings": {
                name: {
                    **learners.learner_class(name).default_settings,
                    **dict(values),
                }
                for name, values in self.settings
            },
        }


def check_bank_folder(out: Path, plan: BankPlan) -> None:
    """Refuse a folder that holds another bank or something else (``ConfigError``)."""
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out} exists and is not a folder")
    path = out / BANK_FILE
    if not path.exists():
        return
    try:
        recorded = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as error:
        raise ConfigError(f"{path} is not a readable bank file: {error}") from None
    expected = json.loads(json.dumps(plan.identity()))  # as the file reads back
    if recorded != expected:
        changed = sorted(
            key for key in set(recorded) | set(expected) if recorded.get(key) != expected.get(key)
        )
        raise ConfigError(
            f"--out {out} holds a bank simulated with other arguments ({', '.join(changed)} "
            "differ); use another folder, or delete this one to start over"
        )


def read_journal(path: Path) -> dict[str, dict[str, Any]]:
    """Journalled sessions by key; a line cut short (a run killed while writing) is dropped."""
    if not path.exists():
        return {}
    rows: dict[str, dict[str, Any]] = {}
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            row = json.loads(line)
            rows.setdefault(str(row["key"]), row)
        except (ValueError, KeyError, TypeError):
            continue
    return rows


def _start_worker(threads: int, environments: tuple[EnvironmentSpec, ...]) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops the pool
    domains.register_all(environments)
    from server.learners.planning import set_planner_threads

    set_planner_threads(threads)


def _results(jobs: Sequence[SessionJob], workers: int) -> Iterator[dict[str, Any]]:
    from server.cores import available_cores, share_threads

    if workers == 1 or len(jobs) <= 1:
        from server.learners.planning import using_planner_threads

        with using_planner_threads(share_threads(available_cores(), 1)):
            for job in jobs:
                yield simulate_session(job)
        return
    processes = min(workers, len(jobs))
    pool = multiprocessing.get_context("spawn").Pool(
        processes,
        initializer=_start_worker,
        initargs=(share_threads(available_cores(), processes), domains.registered()),
    )
    try:
        yield from pool.imap_unordered(simulate_session, jobs, chunksize=1)
        pool.close()
    finally:
        pool.terminate()
        pool.join()


def build_bank(
    plan: BankPlan,
    out: Path,
    workers: int,
    advance: Callable[[int, int], None] = lambda done, total: None,
) -> pd.DataFrame:
    """Simulate the sessions of ``plan`` not yet journalled in ``out`` and return the bank,
    one row per session (``bank_frame``). ``advance(done, total)`` follows the progress."""
    check_bank_folder(out, plan)
    out.mkdir(parents=True, exist_ok=True)
    (out / BANK_FILE).write_text(json.dumps(plan.identity(), indent=2) + "\n", encoding="utf-8")
    journal = out / JOURNAL_FILE
    jobs = plan.jobs()
    finished = read_journal(journal)
    pending = [job for job in jobs if job.key not in finished]
    done = len(jobs) - len(pending)
    advance(done, len(jobs))
    with journal.open("a", encoding="utf-8") as handle:
        for row in _results(pending, workers):
            handle.write(json.dumps(row) + "\n")
            handle.flush()
            os.fsync(handle.fileno())
            finished[row["key"]] = row
            done += 1
            advance(done, len(jobs))
    return bank_frame([finished[job.key] for job in jobs])


def bank_frame(rows: Sequence[dict[str, Any]]) -> pd.DataFrame:
    """The sessions as a table: domain, participant, environment, learner, the participant's
    traits and the curve (a list of [episodes, actions, normalised return])."""
    return pd.DataFrame(list(rows)).drop(columns="key")


def first_reached(curve: Sequence[Sequence[float]], threshold: float) -> tuple[int, int] | None:
    """(episodes, actions) at the first evaluation at or above ``threshold``; None if none."""
    for episodes, actions, value in curve:
        if value >= threshold:
            return int(episodes), int(actions)
    return None
