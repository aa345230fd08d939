"""The platform registry: a fourth platform, registered in a few lines, takes a participant from
its link to the completion code (and another through withdrawal); every list of platform names
is the registry's."""

from __future__ import annotations

from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from server.app import schemas, study_file
from server.app.platform_registry import PLATFORMS, arrival_parameters, names, platform
from server.app.platforms.base import ID_PATTERN, BasePlatform, Handing
from server.app.rights.scrub import with_ids
from server.app.rights.withdrawal import Withdrawal
from server.app.settings import Settings, review_backends
from server.app.storage.db import Database
from server.app.storage.models import Participant as ParticipantRow
from server.app.study_file import StudyConfig, StudyConfigError
from tests.support.server import Participant, demonstrate_each_task, study_config


class Toy(BasePlatform):
    name = "toy"
    display_name = "Toy Crowd"
    parameters = {"TOY_ID": ID_PATTERN, "TOY_TURN": ID_PATTERN}
    ids = {"platform_participant_id": "TOY_ID", "platform_submission_id": "TOY_TURN"}
    done = "Your data has been deleted. Toy Crowd forgets your turn too."

    def handing(self, participant: Any, study: StudyConfig, code: str) -> Handing:
        return Handing(redirect_url=f"https://toy.example/done?code={code}")


@pytest.fixture(autouse=True)
def toy(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(PLATFORMS, "toy", Toy())


@pytest.fixture
def study(toy: None) -> StudyConfig:
    return study_config(completion={"mode": "toy"})


def toy_arrival(client: TestClient, who: str) -> Participant:
    client.cookies.clear()
    arrived = client.post("/api/arrivals", json={"TOY_ID": who, "TOY_TURN": f"T{who}"})
    assert arrived.status_code == 201, arrived.text
    assert arrived.json()["participant"]["platform"] == "toy"
    return Participant(client, arrived.json()["token"])


def test_a_toy_participant_takes_the_study_to_its_completion(
    client: TestClient, db: Database
) -> None:
    participant = toy_arrival(client, "TOY1")
    participant.act("/api/participant/consent", agree=True)
    session_id = participant.act("/api/participant/start")["participant"]["current_session_id"]
    finish = None
    while session_id is not None:
        demonstrate_each_task(participant, session_id)
        finish = participant.act(f"{participant.session(session_id)}/finish")
        session_id = finish["participant"]["current_session_id"]
    assert finish is not None and finish["participant"]["status"] == "completed"
    completion = finish["participant"]["completion"]
    code = completion["code"]
    assert len(code) == 10 and completion == {
        "code": code,
        "mode": "toy",
        "submit_url": None,
        "submit_fields": None,
        "redirect_url": f"https://toy.example/done?code={code}",
    }
    assert participant.act("/api/participant/submission")["participant"]["status"] == "submitted"
    with db.read() as s:
        row = s.scalars(select(ParticipantRow)).one()
        assert (row.platform, row.platform_participant_id, row.platform_submission_id) == (
            "toy",
            "TOY1",
            "TTOY1",
        )
    # The same ids again: the same participant, resumed.
    again = client.post("/api/arrivals", json={"TOY_ID": "TOY1", "TOY_TURN": "TTOY1"})
    assert again.status_code == 200 and again.json()["resumed"]


def test_a_toy_participant_withdraws_and_bad_links_are_refused(client: TestClient) -> None:
    participant = toy_arrival(client, "TOY2")
    answer = client.post("/api/participant/withdrawal", headers=participant.headers)
    assert answer.status_code == 200, answer.text
    assert answer.json() == {"platform": "toy", "message": Toy.done, "redirect_url": None}
    client.cookies.clear()
    for body, status, words in (
        ({"TOY_ID": "TOY3"}, 400, "the Toy Crowd link lacks TOY_TURN"),
        ({"TOY_ID": "TOY3", "TOY_TURN": "T 3"}, 422, "TOY_TURN: String should match pattern"),
        ({"TOY_ID": "TOY3", "TOY_TURN": "T3", "PROLIFIC_PID": "P"}, 400, "both"),
        ({"TOY_ID": "TOY3", "TOY_TURN": "T3", "toy_id": "x"}, 422, "extra"),
        ({}, 403, "This study runs on Toy Crowd"),
        ({"PROLIFIC_PID": "P1", "STUDY_ID": "S1", "SESSION_ID": "X1"}, 403, "not run on Prolific"),
    ):
        response = client.post("/api/arrivals", json=body)
        assert response.status_code == status, (body, response.text)
        assert words in response.text, (body, response.text)
    page = client.get("/study", params={"TOY_ID": "TOY3", "TOY_TURN": "T 3"})
    assert page.status_code == 400 and "TOY_TURN" in page.text


def enum(model: Any, field: str) -> list[str]:
    return list(model.model_json_schema()["properties"][field]["enum"])


def test_every_list_of_platform_names_is_the_registry_s() -> None:
    every = ["lab", "mturk", "prolific", "toy"]
    assert list(names()) == every
    assert enum(study_file.Completion, "mode") == every
    assert enum(schemas.Completion, "mode") == every
    assert enum(schemas.ParticipantState, "platform") == every
    assert enum(Withdrawal, "platform") == every
    assert with_ids() == ["mturk", "prolific", "toy"]
    assert review_backends() == ["replica", "mturk", "prolific"]  # the toy does not review
    assert enum(Settings, "review_backend") == review_backends()
    expected = {k: v for name in every for k, v in platform(name).parameters.items()}
    assert arrival_parameters() == expected
    assert set(schemas.ArrivalRequest.model_json_schema()["properties"]) == set(expected)
    study_config(completion={"mode": "toy"})
    with pytest.raises(StudyConfigError, match=r"completion\.mode"):
        study_config(completion={"mode": "email"})
    with pytest.raises(ValueError, match="review_backend"):
        Settings(database_url="sqlite:///x.db", review_backend="toy")
