"""The simulated teacher's demonstrations of the paper's protocol as Minari datasets, for
offline RL and imitation baselines on the same data our learners get.

For each environment, agent and round, the demonstrations the simulations give (the same
teacher, start states and order: ``protocols.demonstration_streams`` and
``protocols.give_demonstrations``, which depend on the seed, the environment and the agent
only, so every learner of an agent sees them): one episode per demonstration, id
``bam-study/<environment>/simulated-teacher-v0``.
"""

from __future__ import annotations

from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from server import domains, learners
from server.rl.datasets import Dataset, DatasetEpisode, write_datasets

DATASET_NAME = "simulated-teacher"
INFOS: dict[str, str] = {
    "task": "Index of the episode's task (the Gymnasium environment's reset option 'task').",
    "agent": "The simulated agent (the simulations' agent index): its teacher and starts.",
    "round": "The round of the protocol, from 1 (one demonstration per task per round).",
}


class _Recorder:
    """Takes the demonstrations ``give_demonstrations`` hands a learner, as episodes: a new
    one at each task change or where a step does not start from the last one's state."""

    def __init__(self) -> None:
        self.episodes: list[tuple[int, list[int], list[int]]] = []

    def record_demonstration(self, task: int, state: int, action: int, next_state: int) -> None:
        last = self.episodes[-1] if self.episodes else None
        if last is None or last[0] != task or last[1][-1] != state:
            self.episodes.append((task, [state], []))
        _, states, actions = self.episodes[-1]
        states.append(next_state)
        actions.append(action)

    def taken(self) -> list[tuple[int, list[int], list[int]]]:
        return [episode for episode in self.episodes if episode[2]]


def teacher_datasets(
    environments: Sequence[str], agents: int, rounds: int, seed: int
) -> list[Dataset]:
    """One dataset per environment with ``agents`` x ``rounds`` rounds of demonstrations."""
    from server.simulation.protocols import Job, demonstration_streams, give_demonstrations

    if agents < 1 or rounds < 1:
        raise ValueError("agents and rounds must be at least 1")
    when = datetime.now(UTC).isoformat()
    datasets = []
    for environment in environments:
        env = domains.make(environment)
        episodes: list[DatasetEpisode] = []
        for agent in range(agents):
            # The demonstrations depend on (seed, environment, agent) alone: any learner will do.
            job = Job("demonstrations", environment, learners.NAMES[0], agent, rounds, seed)
            teacher, starts = demonstration_streams(job, env)
            for round_ in range(1, rounds + 1):
                recorder = _Recorder()
                give_demonstrations(env, teacher, recorder, starts)  # type: ignore[arg-type]
                for task, states, actions in recorder.taken():
                    length = len(states)
                    episodes.append(
                        DatasetEpisode(
                            task, states, actions, {"agent": [agent] * length,
                                                    "round": [round_] * length}
                        )
                    )  # fmt: skip
        metadata: dict[str, Any] = {
            "protocol": "the paper's demonstrations protocol (section 4.2): per round, one "
            "optimal demonstration per task from the task's start distribution",
            "seed": seed,
            "agents": agents,
            "rounds": rounds,
            "episodes": len(episodes),
            "created_at": when,
            "infos": INFOS,
        }
        datasets.append(
            Dataset(
                environment=environment,
                name=DATASET_NAME,
                episodes=episodes,
                description=f"BAM Study: the simulated teacher's demonstrations in {environment}.",
                algorithm="simulated teacher (hard-max value iteration on the true dynamics)",
                metadata=metadata,
            )
        )
    return datasets


def write_teacher_datasets(
    environments: Sequence[str], agents: int, rounds: int, seed: int, out: Path
) -> list[str]:
    """Write ``teacher_datasets`` into the new folder ``out``; returns the dataset ids."""
    return write_datasets(teacher_datasets(environments, agents, rounds, seed), out)
