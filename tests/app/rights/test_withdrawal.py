"""Withdrawal and erasure on request, by each way in: the participant's "stop and delete my data"
(told how to leave MTurk or Prolific; sent back with the study's NO_CONSENT code when it has
one), the admin API (which the dashboard calls), and ``bam-study erase`` by number, worker id or pseudonym.
Bad requests change nothing."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from server.app.platforms.mturk import MTURK
from server.app.platforms.prolific_platform import PROLIFIC
from server.app.rights.pseudonyms import database_secret, pseudonym
from server.app.storage.db import Database
from server.app.storage.models import Erasure, Participant
from server.app.study_file import StudyConfig
from server.commands.main import main
from tests.support.server import (
    ADMIN_TOKEN,
    TOKEN_HEADER,
    new_participant,
    study_config,
)
from tests.support.server import Participant as ApiParticipant

MTURK_RETURN, PROLIFIC_RETURN = MTURK.done, PROLIFIC.done

ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}


def participants(db: Database) -> list[tuple[int, str | None]]:
    with db.read() as s:
        return [
            (p.id, p.platform_participant_id)
            for p in s.scalars(select(Participant).order_by(Participant.id))
        ]


def erasures(db: Database) -> list[tuple[int, str]]:
    with db.read() as s:
        return [(e.participant_id, e.erased_by) for e in s.scalars(select(Erasure))]


def test_an_mturk_participant_withdraws_and_is_told_how_to_return_the_hit(
    client: TestClient, db: Database
) -> None:
    leaving = new_participant(client, "WLEAVES", "ALEAVES")
    leaving.act("/api/participant/consent", agree=True)
    staying = new_participant(client, "WSTAYS", "ASTAYS")
    (leaving_id, _), (staying_id, _) = participants(db)

    answer = client.post("/api/participant/withdrawal", headers=leaving.headers)
    assert answer.status_code == 200, answer.text
    assert answer.json() == {"platform": "mturk", "message": MTURK_RETURN, "redirect_url": None}
    cleared = answer.headers.get("set-cookie", "")
    assert cleared.startswith(f"{client.app.state.server.settings.cookie_name}=")  # type: ignore[attr-defined]
    assert "max-age=0" in cleared.lower()
    assert participants(db) == [(staying_id, "WSTAYS")]
    assert erasures(db) == [(leaving_id, "participant")]
    # The token is nobody's now: a second withdrawal finds nobody and erases nothing more.
    again = client.post("/api/participant/withdrawal", headers=leaving.headers)
    assert again.status_code == 401
    assert client.get("/api/participant", headers=leaving.headers).status_code == 401
    assert client.post("/api/participant/withdrawal").status_code == 401
    assert participants(db) == [(staying_id, "WSTAYS")]
    assert len(erasures(db)) == 1
    assert staying.get("/api/participant")["status"] == "arrived"


def prolific_arrival(client: TestClient, pid: str) -> str:
    client.cookies.clear()
    arrived = client.post(
        "/api/arrivals", json={"PROLIFIC_PID": pid, "STUDY_ID": "S1", "SESSION_ID": f"SE{pid}"}
    )
    assert arrived.status_code == 201, arrived.text
    return str(arrived.json()["token"])


@pytest.mark.parametrize("no_consent_code", ["C1NOCONSENT", None])
def test_a_prolific_participant_is_sent_back_with_the_no_consent_code(
    no_consent_code: str | None, client: TestClient, db: Database
) -> None:
    completion = {"mode": "prolific", "prolific_code": "C0DONE"}
    if no_consent_code is not None:
        completion["prolific_no_consent_code"] = no_consent_code
    client.app.state.server.study = study_config(completion=completion)  # type: ignore[attr-defined]
    token = prolific_arrival(client, "5f0000000000000000000001")
    answer = client.post("/api/participant/withdrawal", headers={TOKEN_HEADER: token})
    assert answer.status_code == 200, answer.text
    if no_consent_code is None:
        assert answer.json() == {
            "platform": "prolific",
            "message": PROLIFIC_RETURN,
            "redirect_url": None,
        }
    else:
        assert answer.json()["redirect_url"] == (
            f"https://app.prolific.com/submissions/complete?cc={no_consent_code}"
        )
    assert participants(db) == []


def test_the_study_file_checks_the_no_consent_code() -> None:
    from server.app.study_file import StudyConfigError

    with pytest.raises(StudyConfigError, match="prolific_no_consent_code"):
        study_config(
            completion={
                "mode": "prolific",
                "prolific_code": "C0DONE",
                "prolific_no_consent_code": "not a code!",
            }
        )


def test_the_experimenter_erases_from_the_admin_api(
    client: TestClient, db: Database, study: StudyConfig
) -> None:
    for worker in ("W1", "W2", "W3"):
        new_participant(client, worker, f"A{worker}")
    (first, _), (second, _), (third, _) = participants(db)
    assert client.post(f"/api/admin/participants/{first}/erasure").status_code == 401
    assert client.post("/api/admin/participants/99999/erasure", headers=ADMIN).status_code == 404
    assert len(participants(db)) == 3

    erased = client.post(f"/api/admin/participants/{first}/erasure", headers=ADMIN)
    assert erased.status_code == 200, erased.text
    secret = database_secret(db)
    assert erased.json()["platform_participant_pseudonym"] == pseudonym(secret, "W1", "w")
    assert erased.json()["rows"]["participants"] == 1
    again = client.post(f"/api/admin/participants/{second}/erasure", headers=ADMIN)
    assert again.status_code == 200, again.text
    assert participants(db) == [(third, "W3")]
    assert erasures(db) == [(first, "experimenter"), (second, "experimenter")]
    listed = client.get("/api/admin/participants", headers=ADMIN).json()
    assert [p["participant_id"] for p in listed] == [third]


def test_bam_study_erase_by_worker_id_and_pseudonym(
    client: TestClient, db: Database, capsys: pytest.CaptureFixture[str]
) -> None:
    for worker in ("WORKERA", "WORKERB", "WORKERC"):
        new_participant(client, worker, f"A{worker}")
    url = db.engine.url.render_as_string(hide_password=False)
    ids = dict((worker, number) for number, worker in participants(db))
    secret = database_secret(db)

    def erase(*args: str) -> int:
        return main(["erase", "--database-url", url, *args])

    # Without a terminal, it erases only when told --yes.
    assert erase("WORKERA") == 2
    assert "add --yes" in capsys.readouterr().err
    assert erase("NOBODY", "--yes") == 1
    assert capsys.readouterr().err.strip() == (
        "bam-study erase: no participant 'NOBODY' (a participant number, worker id or w_ pseudonym)"
    )
    assert len(participants(db)) == 3

    assert erase("WORKERA", "--yes") == 0
    assert f"participant {ids['WORKERA']}" in capsys.readouterr().out
    assert erase(pseudonym(secret, "WORKERB", "w") or "", "--yes") == 0
    assert erase(str(ids["WORKERC"]), "--yes") == 0
    assert participants(db) == []
    assert [who for who, _ in erasures(db)] == [ids["WORKERA"], ids["WORKERB"], ids["WORKERC"]]
    with db.read() as s:
        assert s.scalar(select(func.count()).select_from(Erasure)) == 3


def test_a_worker_who_withdraws_can_still_return_the_hit_on_the_replica(
    client: TestClient, db: Database
) -> None:
    """MTurk keeps the assignment of a worker a study erases, and the worker is told to return
    the HIT: the replica keeps it (accepted) so that Return works there, and the return changes
    nothing of ours (nobody is left to mark)."""
    from server.app.storage.replica_models import ReplicaAssignment

    accepted = client.post(
        "/mturk/accept", data={"workerId": "WWITHDRAWS"}, headers=ADMIN, follow_redirects=False
    )
    assert accepted.status_code == 303, accepted.text
    with db.read() as s:
        row = s.scalars(
            select(ReplicaAssignment).where(ReplicaAssignment.worker_id == "WWITHDRAWS")
        ).one()
        row_id, link = (
            row.id,
            {
                "assignmentId": row.assignment_id,
                "hitId": row.hit_id,
                "workerId": "WWITHDRAWS",
                "turkSubmitTo": "http://testserver",
            },
        )
    client.cookies.clear()
    arrived = client.post("/api/arrivals", json=link)
    assert arrived.status_code == 201, arrived.text
    worker = ApiParticipant(client, arrived.json()["token"])
    worker.act("/api/participant/consent", agree=True)
    withdrawn = client.post("/api/participant/withdrawal", headers=worker.headers)
    assert withdrawn.json()["message"] == MTURK_RETURN
    assert participants(db) == []
    with db.read() as s:
        kept = s.get(ReplicaAssignment, row_id)
        assert kept is not None and kept.status == "accepted"

    returned = client.post(f"/mturk/work/{row_id}/return", headers=ADMIN, follow_redirects=False)
    assert returned.status_code == 303, returned.text
    with db.read() as s:
        kept = s.get(ReplicaAssignment, row_id)
        assert kept is not None and kept.status == "returned"
    assert participants(db) == [] and len(erasures(db)) == 1
