"""The quality checks built for teaching (``quality.csv``) separate simulated careful teachers
from simulated key-mashers (random moves, random + and -, in a hurry) and idle participants
(careful, but away between agents) by completion time, idle stretches, optimal
demonstrations and attention checks; exceptionally fast is 3 s.d. below the others' mean;
failed attention checks are a ground with two failures (one in a study under five minutes);
each row names the Prolific ground that applies, if any."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import replace

import httpx
import pandas as pd
import pytest
from fastapi.testclient import TestClient

from server.app.export.columns import DICTIONARY
from server.app.export.quality import Thresholds, quality_table
from server.app.export.tables import export_tables
from server.app.main import create_app
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.study_file import StudyConfig
from server.commands.simulated import (
    LightClient,
    ParticipantRun,
    SimulatedParticipant,
    TeachingPlan,
)
from tests.app.rights.test_erasure import study as study
from tests.support.server import (
    ADMIN_TOKEN,
    live,
    make_settings,
    study_config,
    wait_for_updates,
    wait_until_ready,
)

ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
CAREFUL = TeachingPlan(
    min_rounds=2,
    max_rounds=2,
    mistake_probability=0.05,
    agent_try_probability=1.0,
    idle_move_probability=0.0,
    refresh_probability=0.0,
    max_agent_steps=12,
    think_seconds=0.15,
    agent_step_seconds=0.15,
    feedback_alpha=100.0,  # a person who judges each of the agent's moves
)
MASHER = TeachingPlan(
    kind="key-masher",
    min_rounds=2,
    max_rounds=2,
    agent_try_probability=1.0,
    idle_move_probability=0.0,
    refresh_probability=0.0,
    max_agent_steps=36,
)
# Six rounds: about 400 random + and -, enough that chance alone seldom makes the paper's model
# of feedback explain them better than random presses (with n signals about Phi(-0.16 sqrt(n)),
# under 0.1% at 400; the two rounds above give about 140, which leaves it to chance more often).
LONG_MASHER = replace(MASHER, min_rounds=6, max_rounds=6)
IDLE_SECONDS = 20.0
IDLE = replace(CAREFUL, kind="idle", idle_seconds=IDLE_SECONDS)
# Idle for 15 s or more (the simulated idle participant is away 20 s; careful ones never stop).
THRESHOLDS = Thresholds(idle_minutes=0.25)


def take_part(client: TestClient, index: int, plan: TeachingPlan) -> int:
    run = SimulatedParticipant(
        "http://testserver", index, 11, plan, client=TestClient(client.app)
    ).take_part()
    assert run.error is None, run.error
    return index


def by_kind(quality: pd.DataFrame, ids: dict[str, list[int]], column: str) -> dict[str, list]:
    rows = quality.set_index("participant_id")
    return {kind: [rows.loc[i, column] for i in members] for kind, members in ids.items()}


@pytest.fixture
def served(
    db: Database, settings: Settings, study: StudyConfig, executor: ProcessPoolExecutor
) -> Iterator[str]:
    """The study served over HTTP (uvicorn in a thread), ready for its first participant; its
    URL."""
    with live(create_app(settings, study, db=db, executor=executor)) as url:
        with httpx.Client(base_url=url, timeout=60) as client:
            wait_until_ready(client)  # the first participant waits for no update process
        yield url


def take_part_side_by_side(url: str, first: int, plans: list[TeachingPlan]) -> list[int]:
    """Simulated participants ``first``, ``first + 1``, ... taking part at the same time (their
    pauses overlap), each arriving and consenting once the one before has, so that their
    participant ids follow their order as if one came after the other. Their ids."""
    consented = [threading.Event() for _ in range(len(plans) + 1)]
    consented[0].set()

    def one(slot: int) -> ParticipantRun:
        with LightClient(url) as client:
            turn = (consented[slot], consented[slot + 1])
            return SimulatedParticipant(
                url, first + slot, 11, plans[slot], client=client, turn=turn
            ).take_part()

    with ThreadPoolExecutor(len(plans)) as pool:
        runs = list(pool.map(one, range(len(plans))))
    assert [run.error for run in runs] == [None] * len(plans), [run.error for run in runs]
    return [int(run.participant_id or 0) for run in runs]


@pytest.mark.slow  # seven simulated participants, one away for 20 s: about a minute a database
def test_each_check_separates_careful_teachers_from_key_mashers_and_idle_participants(
    served: str, db: Database
) -> None:
    # The careful teachers side by side; the key-masher after them, alone, as it hurries
    # (beside them, its tries would wait for the learners behind theirs).
    careful = take_part_side_by_side(served, 0, [CAREFUL] * 4)
    (masher,) = take_part_side_by_side(served, 4, [MASHER])
    wait_for_updates(db)
    ids = {"careful": careful, "masher": [masher]}
    assert ids == {"careful": [1, 2, 3, 4], "masher": [5]}

    # Completion time: the key-masher is the fastest, and no careful teacher is exceptionally
    # fast. (Four careful teachers on a loaded machine are too few and too uneven for the
    # 3 s.d. rule to be sure of the key-masher: test_exceptionally_fast_... checks the rule.)
    quality = quality_table(export_tables(db), THRESHOLDS)
    minutes = by_kind(quality, ids, "minutes")
    assert minutes["masher"][0] < min(minutes["careful"]), quality.to_string()
    fast = by_kind(quality, ids, "exceptionally_fast")
    assert fast["careful"] == [False] * 4, quality.to_string()

    ids["idle"] = take_part_side_by_side(served, 5, [IDLE])
    wait_for_updates(db)
    assert ids["idle"] == [6]
    quality = quality_table(export_tables(db), THRESHOLDS)
    assert list(quality["participant_id"]) == [1, 2, 3, 4, 5, 6]
    # Idle stretches: only the idle participant's.
    assert by_kind(quality, ids, "long_idle") == {
        "careful": [False] * 4,
        "masher": [False],
        "idle": [True],
    }, quality.to_string()
    idle = quality.set_index("participant_id").loc[6, "longest_idle_minutes"]
    assert idle >= IDLE_SECONDS / 60 - 0.01  # rounded to 0.01 minute
    # Demonstrations: careful teachers (idle ones too) move optimally, key-mashing does not.
    share = by_kind(quality, ids, "optimal_demonstration_share")
    assert min(share["careful"] + share["idle"]) >= 0.85, share
    assert share["masher"][0] < 0.7, share
    assert by_kind(quality, ids, "poor_demonstrations") == {
        "careful": [False] * 4,
        "masher": [True],
        "idle": [False],
    }
    # Feedback: a careful teacher's + and - agree with the worth of the agent's move, and the
    # paper's model of feedback explains them better than random presses; random + and - agree
    # about half the time.
    consistent = by_kind(quality, ids, "consistent_feedback_share")
    assert min(consistent["careful"] + consistent["idle"]) >= 0.7, consistent
    assert consistent["masher"][0] is None or consistent["masher"][0] < 0.6, consistent
    ratio = by_kind(quality, ids, "feedback_log_likelihood_ratio")
    assert min(ratio["careful"] + ratio["idle"]) > 0, ratio
    flagged = by_kind(quality, ids, "inconsistent_feedback")
    assert flagged["careful"] + flagged["idle"] == [False] * 5, quality.to_string()
    # With about 400 random + and -, the key-masher is flagged.
    assert take_part_side_by_side(served, 6, [LONG_MASHER]) == [7]
    wait_for_updates(db)
    long = quality_table(export_tables(db), THRESHOLDS).set_index("participant_id").loc[7]
    assert long["feedback_signals"] >= 300, long
    assert long["feedback_log_likelihood_ratio"] < 0 and long["inconsistent_feedback"], long
    # No flag but the completion time makes a Prolific ground; poor teaching is none.
    grounds = quality.set_index("participant_id")["prolific_ground"]
    assert set(grounds.drop(5)) == {"none"}
    assert grounds.loc[5] == (
        "TOO_QUICKLY"
        if quality.set_index("participant_id").loc[5, "exceptionally_fast"]
        else "none"
    )
    flags = quality.set_index("participant_id")["flags"]
    assert all(
        "poor_demonstrations" not in f and "long_idle" not in f for f in flags.loc[[1, 2, 3, 4]]
    )
    assert "long_idle" in flags.loc[6] and "poor_demonstrations" in flags.loc[5]

    # The analysis leaves out whom a chosen check flags, reading the database itself.
    from analysis.data import load_database

    url = db.engine.url.render_as_string(hide_password=False)
    notes: list[str] = []
    sessions, _ = load_database(url, exclude_flagged=("poor_demonstrations",), notes=notes)
    assert set(sessions["participant_id"].astype(int)) == {1, 2, 3, 4, 6}
    assert any("flagged poor_demonstrations in the quality checks" in note for note in notes)


def test_quality_csv_is_in_the_export_the_dictionary_and_the_admin_api(
    client: TestClient, db: Database
) -> None:
    before = client.get("/api/admin/participants/1/quality", headers=ADMIN)
    assert before.status_code == 404
    take_part(client, 0, CAREFUL)
    wait_for_updates(db)
    shown = client.get("/api/admin/participants/1/quality", headers=ADMIN)
    assert shown.status_code == 200, shown.text
    assert list(shown.json()) == list(DICTIONARY["quality"])
    assert shown.json()["participant_id"] == 1 and shown.json()["minutes_z"] is None
    assert shown.json()["prolific_ground"] == "none"
    assert client.get("/api/admin/participants/1/quality").status_code == 401
    tables = export_tables(db)
    assert list(tables["quality"].columns) == list(DICTIONARY["quality"])
    assert list(tables["quality"]["participant_id"]) == [1]
    # One participant: no distribution to compare with.
    assert pd.isna(tables["quality"].loc[0, "minutes_z"])
    assert not tables["quality"].loc[0, "exceptionally_fast"]


def test_exceptionally_fast_is_3_sd_below_the_others_mean() -> None:
    """Exceptionally fast is judged against the other participants' mean and s.d."""
    minutes = [20.0, 21.0, 19.0, 20.5, 19.5, 12.0]
    tables = {
        "participants": pd.DataFrame(
            {
                "participant_id": range(1, 7),
                "minutes": minutes,
                "completed_at": ["2026-01-01T00:00:00+00:00"] * 6,
            }
        ),
        "sessions": pd.DataFrame({"session_id": [], "environment": []}),
        "events": pd.DataFrame(
            columns=[
                "event_id", "participant_id", "session_id", "created_at", "record", "task",
                "state", "action", "feedback",
            ]
        ),
    }  # fmt: skip
    quality = quality_table(tables).set_index("participant_id")
    assert list(quality["exceptionally_fast"]) == [False] * 5 + [True]
    assert quality.loc[6, "minutes_z"] < -3 < quality.loc[1, "minutes_z"]
    assert list(quality["prolific_ground"]) == ["none"] * 5 + ["TOO_QUICKLY"]


def test_attention_checks_separate_key_mashers_from_careful_and_idle_participants(
    db: Database, executor: ProcessPoolExecutor
) -> None:
    """Two agents with a check between them (robot and star eight moves apart, ten moves
    allowed): careful and idle participants pass it, a key-masher's random arrows fail it, and
    in this short study one failed check is Prolific's FAILED_CHECK."""
    study = study_config(
        learners=["cloning"],
        agents_per_environment=2,
        domains=[{"name": "navigation", "environments": ["wall"]}],
        tutorial={"enabled": False},
        attention_checks={"enabled": True, "start": [4, 0], "star": [0, 4], "moves": 10},
    )
    quick = {"min_rounds": 1, "max_rounds": 1, "agent_try_probability": 0.0}
    plans = {
        "careful": replace(CAREFUL, **quick),
        "masher": replace(MASHER, **quick),
        "idle": replace(IDLE, **quick, idle_seconds=0.1),
    }
    settings = make_settings(db.engine.url.render_as_string(hide_password=False))
    app = create_app(settings, study, db=db, executor=executor)
    with TestClient(app):
        runs = {}
        for index, (kind, plan) in enumerate(plans.items()):
            run = SimulatedParticipant(
                "http://testserver", index, 11, plan, client=TestClient(app)
            ).take_part()
            assert run.error is None, run.error
            runs[kind] = run
        wait_for_updates(db)
        tables = export_tables(db)
    assert {kind: (run.attention_checks, run.failed_checks) for kind, run in runs.items()} == {
        "careful": (1, 0),
        "masher": (1, 1),
        "idle": (1, 0),
    }
    checks = tables["attention_checks"].set_index("participant_id")
    assert list(checks["outcome"]) == ["passed", "failed", "passed"]
    assert checks.loc[1, "moves"] == "UP UP UP UP RIGHT RIGHT RIGHT RIGHT"
    assert checks.loc[2, "moves_made"] == 10 and checks.loc[2, "after_position"] == 0
    quality = quality_table(tables).set_index("participant_id")
    assert list(quality["attention_checks"]) == [1, 1, 1]
    assert list(quality["failed_attention_checks"]) == [0, 1, 0]
    assert list(quality["failed_attention"]) == [False, True, False]
    assert "failed_attention" in quality.loc[2, "flags"]
    assert list(quality["prolific_ground"]) == ["none", "FAILED_CHECK", "none"]


def test_failed_check_needs_two_failures_in_a_study_of_five_minutes_or_more() -> None:
    failed = [0, 1, 2, 1]
    tables = {
        "participants": pd.DataFrame(
            {
                "participant_id": range(1, 5),
                "minutes": [20.0, 21.0, 19.0, 20.0],
                "completed_at": ["2026-01-01T00:00:00+00:00"] * 4,
            }
        ),
        "sessions": pd.DataFrame({"session_id": [], "environment": []}),
        "events": pd.DataFrame(
            columns=[
                "event_id", "participant_id", "session_id", "created_at", "record", "task",
                "state", "action", "feedback",
            ]
        ),
        "attention_checks": pd.DataFrame(
            {
                "participant_id": [p for p in range(1, 5) for _ in range(3)],
                "outcome": [
                    outcome
                    for p in range(1, 5)
                    for outcome in ["failed"] * failed[p - 1] + ["passed"] * (3 - failed[p - 1])
                ],
            }
        ),
    }  # fmt: skip
    # A study of about 20 minutes (the median): one failure is not enough.
    quality = quality_table(tables).set_index("participant_id")
    assert list(quality["failed_attention_checks"]) == failed
    assert list(quality["attention_checks"]) == [3] * 4
    assert list(quality["failed_attention"]) == [False, False, True, False]
    assert list(quality["prolific_ground"]) == ["none", "none", "FAILED_CHECK", "none"]
    # A study under five minutes: one failure is.
    short = quality_table(tables, Thresholds(study_minutes=4.0)).set_index("participant_id")
    assert list(short["prolific_ground"]) == [
        "none",
        "FAILED_CHECK",
        "FAILED_CHECK",
        "FAILED_CHECK",
    ]
    # Exactly five minutes is a study of five minutes or more.
    five = quality_table(tables, Thresholds(study_minutes=5.0)).set_index("participant_id")
    assert list(five["failed_attention"]) == [False, False, True, False]
    # An export made before attention checks existed has none.
    del tables["attention_checks"]
    older = quality_table(tables).set_index("participant_id")
    assert list(older["attention_checks"]) == [0] * 4
