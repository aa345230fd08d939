"""``bam-study export --format minari``: a simulated study exported both ways has the same
episodes and actions in Minari as in episodes.csv and events.csv; the datasets replay on their
recovered Gymnasium environment; a cloning learner fitted from them equals, to the last bit, one
fitted from the database's events; an empty database, an unknown format and a folder holding
an older export each fail clearly and write nothing."""

from __future__ import annotations

import hashlib
from collections import defaultdict
from datetime import datetime
from pathlib import Path
from typing import Any

import minari
import numpy as np
import pandas as pd
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from server import domains, learners
from server.app.export.minari import INFOS
from server.app.storage.db import Database
from server.app.storage.models import Event, LearnerUpdate, LearningSession
from server.app.study_file import DEFAULT_STUDY_CONFIG
from server.app.updates.policies import decode
from server.app.updates.worker import apply_records, records_of
from server.commands.main import main
from server.commands.simulated import SimulatedParticipant, TeachingPlan
from server.domains.base import ACTIONS, STAY
from server.rl import environment_id
from server.rl.datasets import Dataset, DatasetEpisode, write_datasets
from tests.rl._support import run_python
from tests.support.server import ADMIN_TOKEN, wait_for_updates

PLAN = TeachingPlan(min_rounds=1, max_rounds=2, agent_try_probability=0.7, max_agent_steps=10)


@pytest.fixture
def study_run(client: TestClient, db: Database) -> dict[str, Any]:
    """Three simulated participants, the second excluded by the experimenter."""
    runs = [
        SimulatedParticipant(
            "http://testserver", index, 11, PLAN, client=TestClient(client.app)
        ).take_part()
        for index in range(3)
    ]
    assert [run.error for run in runs] == [None, None, None]
    wait_for_updates(db)
    excluded = runs[1].participant_id
    response = client.post(
        f"/api/admin/participants/{excluded}/exclusion",
        json={"reason": "test"},
        headers={"Authorization": f"Bearer {ADMIN_TOKEN}"},
    )
    assert response.status_code == 200, response.text
    return {"url": db.engine.url.render_as_string(hide_password=False), "excluded": excluded}


def export(url: str, out: Path, *flags: str) -> None:
    assert main(["export", "--database-url", url, "--out", str(out), *flags]) == 0


def load(folder: Path, monkeypatch: pytest.MonkeyPatch) -> dict[str, minari.MinariDataset]:
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(folder))
    return {i: minari.load_dataset(i) for i in minari.list_local_datasets()}


def steps_of(episode: Any) -> list[tuple[int, int, int, bool]]:
    """(state, action, next state, synthetic STAY) of each step of a Minari episode."""
    states = episode.observations
    return [
        (int(states[t]), int(episode.actions[t]), int(states[t + 1]),
         bool(episode.infos["synthetic_stay"][t + 1]))
        for t in range(len(episode.actions))
    ]  # fmt: skip


def test_the_minari_export_has_the_csv_exports_episodes_and_actions(
    study_run: dict[str, Any],
    db: Database,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    url = study_run["url"]
    export(url, tmp_path / "csv")
    export(url, tmp_path / "minari", "--format", "minari")
    csv = {name: pd.read_csv(tmp_path / "csv" / f"{name}.csv") for name in ("episodes", "events")}
    for frame in csv.values():  # a study session's rows by session_id, a tutorial's by the other
        frame["session"] = frame["session_id"].fillna(frame["tutorial_session_id"]).astype("Int64")
    participants = pd.read_csv(tmp_path / "csv" / "participants.csv").set_index("participant_id")
    sessions = pd.concat(
        [pd.read_csv(tmp_path / "csv" / f"{n}.csv") for n in ("sessions", "tutorial_sessions")]
    ).set_index("session_id")
    episodes = csv["episodes"].dropna(subset=["ended_at"])
    episodes = episodes[episodes["participant_id"] != study_run["excluded"]]
    environment_of = sessions["environment"]
    expected_ids = {f"bam-study/{environment_of[s]}/participants-v0" for s in episodes["session"]}
    datasets = load(tmp_path / "minari", monkeypatch)
    assert set(datasets) == expected_ids

    # The events.csv steps of each episode, and the synthetic STAY of its end.
    events = csv["events"]
    by_episode: dict[tuple[int, int], list[tuple[int, int, int, bool]]] = defaultdict(list)
    for row in events.itertuples():
        if row.record in ("demonstration", "agent_step"):
            by_episode[(row.session, int(row.episode_index))].append(
                (int(row.state), ACTIONS.index(row.action), int(row.next_state), False)
            )
        if not pd.isna(row.stay_state):
            by_episode[(row.session, int(row.episode_index))].append(
                (int(row.next_state), STAY, int(row.stay_state), True)
            )
    with db.read() as s:
        policies = {
            (u.session_id, u.update_index): u.greedy_policy
            for u in s.scalars(select(LearnerUpdate).where(LearnerUpdate.status == "done"))
        }
    seen: list[int] = []
    agent_steps = feedback_given = 0
    for dataset_id, dataset in datasets.items():
        environment = dataset_id.split("/")[1]
        env = domains.make(environment)
        gym_env = dataset.recover_environment()
        assert gym_env.spec.id == environment_id(environment)
        mine = episodes[episodes["session"].map(environment_of) == environment]
        assert dataset.total_episodes == len(mine)
        for episode in dataset.iterate_episodes():
            infos = episode.infos
            row = mine.set_index("episode_id").loc[int(infos["episode"][0])]
            seen.append(int(infos["episode"][0]))
            assert infos["kind"][0].decode() == row["kind"]
            assert int(infos["task"][0]) == row["task"]
            assert int(infos["session"][0]) == row["session"]
            assert int(infos["participant"][0]) == row["participant_id"]
            session = sessions.loc[row["session"]]
            assert infos["learner"][0].decode() == session["learner"]
            worker = participants.loc[row["participant_id"], "platform_participant_id"]
            assert infos["worker"][0].decode() == worker and worker.startswith("w_")
            steps = steps_of(episode)
            assert steps == by_episode[(row["session"], row["index"])]
            assert steps[0][0] == row["start_state"] and steps[-1][2] == row["end_state"]
            assert sum(not synthetic for *_, synthetic in steps) == row["actions"]
            assert not episode.terminations.any() and episode.truncations[-1]
            assert not episode.truncations[:-1].any()
            # The recovered environment replays it: the same successors, the same rewards.
            gym_env.reset(seed=0, options={"task": int(row["task"])})
            gym_env.unwrapped.state = int(episode.observations[0])
            for t, action in enumerate(episode.actions):
                state, reward, *_ = gym_env.step(int(action))
                assert state == episode.observations[t + 1]
                assert reward == episode.rewards[t]
            # An agent step's action is its learner update's greedy policy's.
            update = infos["learner_update"]
            if row["kind"] == "agent":
                policy = decode(policies[(row["session"], int(update[1]))], env)
                for t, (state, action, _, _) in enumerate(steps):
                    assert update[t + 1] == update[1] >= 0
                    assert policy[int(row["task"]), state] == action
                agent_steps += len(steps)
                feedback_given += int(np.count_nonzero(infos["feedback"]))
            else:
                assert (update == -1).all() and not infos["feedback"].any()
        metadata = dataset.storage.metadata
        assert metadata["study_file"] == "study.toml"
        assert (
            metadata["study_sha256"]
            == hashlib.sha256(DEFAULT_STUDY_CONFIG.read_bytes()).hexdigest()
        )
        assert metadata["participants"] == mine["participant_id"].nunique()
        assert metadata["episodes"] == len(mine)
        assert metadata["demonstrations"] == int((mine["kind"] == "demonstration").sum())
        assert metadata["agent_episodes"] == int((mine["kind"] == "agent").sum())
        assert metadata["excluded_participants"] == "left out"
        assert set(metadata["infos"]) == set(INFOS) == set(episode.infos)
        datetime.fromisoformat(metadata["exported_at"])
    assert sorted(seen) == sorted(episodes["episode_id"])
    assert agent_steps > 0 and feedback_given > 0

    # The excluded participant's episodes, when asked for.
    export(url, tmp_path / "all", "--format", "minari", "--include-excluded")
    every = load(tmp_path / "all", monkeypatch)
    total = sum(d.total_episodes for d in every.values())
    assert total == len(csv["episodes"].dropna(subset=["ended_at"])) > len(episodes)
    check_a_new_program_loads_them(tmp_path / "minari")
    check_an_older_export_is_kept(url, tmp_path / "minari", capsys)


def check_a_new_program_loads_them(folder: Path) -> None:
    """minari.load_dataset and recover_environment with no import of ours."""
    program = (
        "import minari\n"
        "for dataset_id in minari.list_local_datasets():\n"
        "    dataset = minari.load_dataset(dataset_id)\n"
        "    env = dataset.recover_environment()\n"
        "    episode = next(dataset.iterate_episodes())\n"
        "    print(dataset_id, env.spec.id, env.observation_space.contains(episode.observations[0]))\n"
    )
    out = run_python(program, MINARI_DATASETS_PATH=str(folder))
    lines = [line.split() for line in out.splitlines()]
    assert lines and all(
        gym_id == environment_id(dataset_id.split("/")[1]) and contains == "True"
        for dataset_id, gym_id, contains in lines
    )


def test_a_cloning_learner_from_minari_equals_the_one_from_the_database(
    study_run: dict[str, Any], db: Database, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    export(study_run["url"], tmp_path / "data", "--format", "minari")
    datasets = load(tmp_path / "data", monkeypatch)
    checked = 0
    for dataset_id, dataset in datasets.items():
        environment = dataset_id.split("/")[1]
        env = domains.make(environment)
        from_minari = learners.make("cloning", env, seed=0, steps=30)
        for episode in dataset.iterate_episodes():
            task = int(episode.infos["task"][0])
            agent = episode.infos["kind"][0] == b"agent"
            for t, (state, action, next_state, _) in enumerate(steps_of(episode)):
                if agent:
                    feedback = int(episode.infos["feedback"][t + 1])
                    from_minari.record_agent_step(task, state, action, next_state, feedback)
                else:
                    from_minari.record_demonstration(task, state, action, next_state)
        from_database = learners.make("cloning", env, seed=0, steps=30)
        with db.read() as s:
            session_ids = s.scalars(
                select(LearningSession.id)
                .where(
                    LearningSession.environment == environment,
                    LearningSession.participant_id != study_run["excluded"],
                )
                .order_by(LearningSession.id)
            ).all()
            for session_id in session_ids:
                rows = s.execute(
                    select(
                        Event.record, Event.task, Event.state, Event.action, Event.next_state,
                        Event.feedback, Event.stay_state,
                    )
                    .where(Event.session_id == session_id)
                    .order_by(Event.id)
                ).all()  # fmt: skip
                apply_records(from_database, records_of(rows))
        assert np.array_equal(from_minari.data.demonstrations, from_database.data.demonstrations)
        assert np.array_equal(from_minari.data.agent_steps, from_database.data.agent_steps)
        from_minari.update()
        from_database.update()
        assert from_minari.table.tobytes() == from_database.table.tobytes()
        assert np.abs(from_minari.table).max() > 0
        checked += int(np.count_nonzero(from_minari.data.agent_steps[:, 4]) > 0)
    assert checked > 0  # feedback took part in at least one


def folder_state(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def check_an_older_export_is_kept(
    url: str, folder: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Exporting into a folder that holds an export is refused; the folder is left as it was
    and nothing is written beside it."""
    before = folder_state(folder)
    beside = sorted(p.name for p in folder.parent.iterdir())
    capsys.readouterr()
    assert main(["export", "--database-url", url, "--out", str(folder),
                 "--format", "minari"]) == 1  # fmt: skip
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "already holds Minari datasets (bam-study/" in error
    assert folder_state(folder) == before
    assert sorted(p.name for p in folder.parent.iterdir()) == beside


def test_an_empty_database_is_refused_and_nothing_is_written(
    db: Database, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    url = db.engine.url.render_as_string(hide_password=False)
    out = tmp_path / "out"
    assert main(["export", "--database-url", url, "--out", str(out), "--format", "minari"]) == 1
    error = capsys.readouterr().err
    assert error == "bam-study export: the database holds no ended episode to export\n"
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_an_unknown_format_is_refused_and_nothing_is_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as stopped:
        main(["export", "--database-url", "sqlite:///x.db", "--out", str(out), "--format", "rlds"])
    assert stopped.value.code == 2
    error = capsys.readouterr().err.replace("'", "")
    assert "argument --format: invalid choice: rlds (choose from csv, minari, " in error
    assert list(tmp_path.iterdir()) == []
    flag = "--include-excluded"
    assert main(["export", "--database-url", "sqlite:///x.db", "--out", str(out), flag]) == 2
    assert "applies to --format minari only" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_a_failure_while_writing_leaves_nothing_behind(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def episode(task: int) -> DatasetEpisode:
        env = domains.make("wall")
        start = int(np.flatnonzero(env.tasks[task].start)[0])
        return DatasetEpisode(task, [start, start], [STAY], {"kind": ["agent", "agent"]})

    datasets = [
        Dataset("wall", "test", [episode(0)], "first", "none"),
        Dataset("doorway", "test", [episode(0)], "second", "none"),
    ]
    written = write_datasets(datasets, tmp_path / "ok")
    assert written == ["bam-study/wall/test-v0", "bam-study/doorway/test-v0"]
    original = DatasetEpisode.buffer

    def fail_on_doorway(self: DatasetEpisode, environment: str) -> Any:
        if environment == "doorway":
            raise OSError("disk full")
        return original(self, environment)

    monkeypatch.setattr(DatasetEpisode, "buffer", fail_on_doorway)
    with pytest.raises(OSError, match="disk full"):
        write_datasets(datasets, tmp_path / "failed")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ok"]
