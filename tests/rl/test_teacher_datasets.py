"""The simulated teacher's demonstrations as Minari datasets: the demonstrations the
simulations give each agent, one episode each, in order, replaying on the recovered
environment."""

from __future__ import annotations

from pathlib import Path

import minari
import numpy as np
import pytest

from server import domains, learners
from server.rl import environment_id
from server.rl.teacher_datasets import write_teacher_datasets
from server.simulation.protocols import Job, demonstration_streams, give_demonstrations

ENVIRONMENTS = ("doorway", "three-fields")


def test_the_datasets_hold_the_demonstrations_the_simulations_give(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    agents, rounds, seed = 2, 3, 5
    ids = write_teacher_datasets(ENVIRONMENTS, agents, rounds, seed, tmp_path / "data")
    assert ids == [f"bam-study/{name}/simulated-teacher-v0" for name in ENVIRONMENTS]
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "data"))
    for name in ENVIRONMENTS:
        env = domains.make(name)
        dataset = minari.load_dataset(f"bam-study/{name}/simulated-teacher-v0")
        assert dataset.total_episodes == agents * rounds * len(env.tasks)
        gym_env = dataset.recover_environment()
        assert gym_env.spec.id == environment_id(name)
        rows: dict[int, list[tuple[int, int, int, int]]] = {a: [] for a in range(agents)}
        for episode in dataset.iterate_episodes():
            task, agent = int(episode.infos["task"][0]), int(episode.infos["agent"][0])
            gym_env.reset(seed=0, options={"task": task})
            gym_env.unwrapped.state = int(episode.observations[0])
            for t, action in enumerate(episode.actions):
                state, reward, *_ = gym_env.step(int(action))
                assert state == episode.observations[t + 1] and reward == episode.rewards[t]
                rows[agent].append((task, int(episode.observations[t]), int(action), int(state)))
        for agent in range(agents):
            # What a learner of this agent is given in the simulations, round by round.
            learner = learners.make("cloning", env)
            teacher, starts = demonstration_streams(
                Job("demonstrations", name, "bam", agent, rounds, seed), env
            )
            for _ in range(rounds):
                give_demonstrations(env, teacher, learner, starts)
            assert np.array_equal(np.array(rows[agent]), learner.data.demonstrations)


def test_simulate_keeps_the_demonstrations_as_minari_datasets(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``bam-study simulate ... --minari DIR`` writes the same datasets as
    ``write_teacher_datasets`` for the run's environments, agents, rounds and seed; an existing
    folder is refused before anything runs."""
    from server.commands.main import main
    from tests.simulation.conftest import AGENTS, ROUNDS, small_args

    out, data = tmp_path / "run", tmp_path / "minari"
    assert main(small_args(out, "demonstrations", "--minari", str(data))) == 0
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(data))
    for name in ("wall", "doorway"):
        dataset = minari.load_dataset(f"bam-study/{name}/simulated-teacher-v0")
        assert dataset.total_episodes == AGENTS * ROUNDS * len(domains.make(name).tasks)
    again = tmp_path / "again"
    assert main(small_args(again, "demonstrations", "--minari", str(data))) == 2
    assert not again.exists()
