"""The device check before consent (``[device_check]``): the server judges the page's report; a
device that cannot take part is turned away (status incompatible, the reasons in its status
change), on Prolific with the study's INCOMPATIBLE_DEVICE code, and counted in the export; a
device that can stays at the consent page."""

from __future__ import annotations

import csv
import io
import zipfile
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from server.app.participants.device import browser_name
from server.app.platforms.prolific import INCOMPATIBLE_DEVICE_REASON, draft_study
from server.app.storage.db import Database
from server.app.storage.models import Participant, StatusChange
from server.app.study_file import StudyConfig
from tests.support.server import ADMIN_TOKEN, TOKEN_HEADER, new_participant, study_config

ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
CHECKED = {"enabled": True, "min_width": 1000, "min_height": 600, "key_seconds": 30}
FIREFOX = "Mozilla/5.0 (X11; Linux x86_64; rv:128.0) Gecko/20100101 Firefox/128.0"


@pytest.fixture
def study() -> StudyConfig:
    return study_config(device_check=CHECKED)


def report(**changes: Any) -> dict[str, Any]:
    return {"arrow_key": True, "width": 1280, "height": 800, "missing": [], **changes}


def status_notes(db: Database, participant_id: int) -> list[tuple[str, str | None]]:
    with db.read() as s:
        rows = s.scalars(
            select(StatusChange)
            .where(StatusChange.participant_id == participant_id)
            .order_by(StatusChange.id)
        )
        return [(row.status, row.note) for row in rows]


def only_participant(db: Database) -> Participant:
    with db.read() as s:
        (participant,) = s.scalars(select(Participant)).all()
        s.expunge(participant)
        return participant


def test_a_device_that_passes_stays_at_consent_and_may_consent(
    client: TestClient, db: Database
) -> None:
    participant = new_participant(client)
    answer = participant.act("/api/participant/device-check", **report())
    assert answer["kind"] == "device_check"
    assert answer["participant"]["status"] == "arrived"
    assert participant.get("/api/participant")["status"] == "arrived"
    consented = participant.act("/api/participant/consent", agree=True)
    assert consented["participant"]["status"] == "consented"
    # Checked once, before consent.
    again = participant.post("/api/participant/device-check", **report())
    assert again.status_code == 409
    assert "before consent" in again.json()["detail"]


@pytest.mark.parametrize(
    ("changes", "reason"),
    [
        ({"arrow_key": False}, "no arrow key was pressed"),
        (
            {"width": 800, "height": 600},
            "the window is 800x600, smaller than the 1000x600 the study needs",
        ),
        ({"height": 599}, "the window is 1280x599, smaller than the 1000x600"),
        ({"missing": ["dialog", "svg"]}, "the browser lacks dialogs, SVG drawing"),
    ],
)
def test_a_device_that_fails_is_turned_away_with_its_reasons(
    changes: dict[str, Any], reason: str, client: TestClient, db: Database
) -> None:
    participant = new_participant(client)
    response = client.post(
        "/api/participant/device-check",
        json={"seq": 1, **report(**changes)},
        headers={**participant.headers, "User-Agent": FIREFOX},
    )
    assert response.status_code == 200, response.text
    assert response.json()["participant"]["status"] == "incompatible"
    # MTurk: no code; the page asks the worker to return the HIT.
    assert response.json()["participant"]["completion"] is None
    (arrived, turned_away) = status_notes(db, only_participant(db).id)
    assert arrived[0] == "arrived"
    assert turned_away[0] == "incompatible"
    assert turned_away[1] is not None and reason in turned_away[1]
    assert turned_away[1].endswith("(Firefox 128)")
    # The flow ends there: no consent.
    participant.seq = 2
    refused = participant.post("/api/participant/consent", agree=True)
    assert refused.status_code == 409


def test_a_worker_turned_away_may_come_back_on_another_device(client: TestClient) -> None:
    first = new_participant(client, "WDEVICE", "A1")
    first.act("/api/participant/device-check", **report(width=640, height=480))
    client.cookies.clear()
    again = new_participant(client, "WDEVICE", "A2")  # a new assignment, another device
    assert again.act("/api/participant/device-check", **report())["participant"]["status"] == (
        "arrived"
    )


def test_prolific_sends_the_participant_back_with_the_incompatible_device_code(
    client: TestClient, db: Database
) -> None:
    client.app.state.server.study = study_config(  # type: ignore[attr-defined]
        device_check=CHECKED,
        completion={
            "mode": "prolific",
            "prolific_code": "C0DONE",
            "prolific_incompatible_device_code": "C0DEVICE",
        },
    )
    arrived = client.post(
        "/api/arrivals",
        json={"PROLIFIC_PID": "5f" + "0" * 22, "STUDY_ID": "S1", "SESSION_ID": "SE1"},
    )
    token = arrived.json()["token"]
    answer = client.post(
        "/api/participant/device-check",
        json={"seq": 1, **report(arrow_key=False)},
        headers={TOKEN_HEADER: token},
    )
    assert answer.status_code == 200, answer.text
    completion = answer.json()["participant"]["completion"]
    assert completion["code"] == "C0DEVICE"
    assert completion["redirect_url"] == (
        "https://app.prolific.com/submissions/complete?cc=C0DEVICE"
    )
    read = client.get("/api/participant/completion", headers={TOKEN_HEADER: token})
    assert read.status_code == 200 and read.json()["code"] == "C0DEVICE"


def test_prolific_create_sends_the_incompatible_device_code() -> None:
    study = study_config(
        completion={
            "mode": "prolific",
            "prolific_code": "C0DONE",
            "prolific_no_consent_code": "C0NOCONS",
            "prolific_incompatible_device_code": "C0DEVICE",
        },
        prolific={
            "name": "Teach a robot",
            "description": "Teach simple simulated robots with the arrow keys.",
            "places": 10,
            "reward": 6.0,
            "estimated_minutes": 30,
            "maximum_minutes": 90,
            "public_url": "https://study.example.org",
        },
    )
    codes = draft_study(study, 5)["completion_codes"]
    assert [code["code_type"] for code in codes] == [
        "COMPLETED",
        "NO_CONSENT",
        "INCOMPATIBLE_DEVICE",
    ]
    assert codes[2]["code"] == "C0DEVICE"
    assert codes[2]["actions"] == [
        {"action": "REQUEST_RETURN", "return_reason": INCOMPATIBLE_DEVICE_REASON}
    ]
    without = study.model_copy(
        update={
            "completion": study.completion.model_copy(
                update={"prolific_incompatible_device_code": None}
            )
        }
    )
    assert "INCOMPATIBLE_DEVICE" not in [
        c["code_type"] for c in draft_study(without, 5)["completion_codes"]
    ]


def test_the_export_counts_the_participants_turned_away(client: TestClient) -> None:
    turned_away = new_participant(client, "W1", "A1")
    turned_away.act("/api/participant/device-check", **report(arrow_key=False))
    client.cookies.clear()
    passing = new_participant(client, "W2", "A2")
    passing.act("/api/participant/device-check", **report())
    exported = client.get("/api/admin/export.zip", headers=ADMIN)
    assert exported.status_code == 200, exported.text
    with zipfile.ZipFile(io.BytesIO(exported.content)) as archive:
        name = next(n for n in archive.namelist() if n.endswith("participants.csv"))
        rows = list(csv.DictReader(io.StringIO(archive.read(name).decode("utf-8"))))
    by_status = sorted((row["status"], bool(row["incompatible_at"])) for row in rows)
    assert by_status == [("arrived", False), ("incompatible", True)]


def test_a_study_without_the_check_refuses_the_report(client: TestClient) -> None:
    client.app.state.server.study = study_config()  # type: ignore[attr-defined]
    participant = new_participant(client)
    refused = participant.post("/api/participant/device-check", **report())
    assert refused.status_code == 409
    assert refused.json()["detail"] == "this study has no device check"


def test_the_report_s_values_are_checked(client: TestClient) -> None:
    participant = new_participant(client)
    for bad in (report(width=-1), report(missing=["gps"]), report(arrow_key="yes")):
        assert participant.post("/api/participant/device-check", **bad).status_code == 422
    assert participant.get("/api/participant")["status"] == "arrived"


@pytest.mark.parametrize(
    ("user_agent", "name"),
    [
        (FIREFOX, "Firefox 128"),
        (
            "Mozilla/5.0 (X11; Linux x86_64) AppleWebKit/537.36 (KHTML, like Gecko) "
            "Chrome/120.0.0.0 Safari/537.36",
            "Chrome 120",
        ),
        (
            "Mozilla/5.0 (Windows NT 10.0; Win64; x64) AppleWebKit/537.36 (KHTML, like Gecko) "
            "Chrome/120.0.0.0 Safari/537.36 Edg/120.0.2210.91",
            "Edge 120",
        ),
        (
            "Mozilla/5.0 (iPhone; CPU iPhone OS 17_1 like Mac OS X) AppleWebKit/605.1.15 "
            "(KHTML, like Gecko) Version/17.1 Mobile/15E148 Safari/604.1",
            "Safari 17",
        ),
        (None, "another browser"),
    ],
)
def test_the_browser_is_named_by_its_family_and_major_version(
    user_agent: str | None, name: str
) -> None:
    assert browser_name(user_agent) == name
