"""The post-study questionnaire of a study file (``server/examples/questionnaire-study.toml``):
asked after the last agent and before the completion code, answers validated (nothing stored
for a bad one), stored and exported; the paper's study has none and ends as before."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from server.app.export.files import dictionary_frame
from server.app.export.tables import export_tables
from server.app.storage.db import Database
from server.app.storage.models import QuestionnaireAnswer, StatusChange
from server.app.study_file import (
    DEFAULT_STUDY_CONFIG,
    StudyConfig,
    StudyConfigError,
    load_study_config,
    parse_study_config,
)
from tests.support.server import FAST_LEARNERS, Participant, demonstrate_each_task

EXAMPLE = Path(__file__).resolve().parents[3] / "server" / "examples" / "questionnaire-study.toml"
GOOD = {"difficulty": 4, "best_agent": "I could not tell", "comments": "The wall was clear."}


def example_data(**changes: Any) -> dict[str, Any]:
    data = tomllib.loads(EXAMPLE.read_text(encoding="utf-8"))
    data["learner_settings"] = FAST_LEARNERS
    data.update(changes)
    return data


@pytest.fixture
def study() -> StudyConfig:
    """The example study with one agent and no tutorial, so that the questionnaire comes
    after a few requests."""
    return parse_study_config(
        example_data(learners=["cloning"], tutorial={"enabled": False}), "questionnaire study"
    )


def lab_participant_after_the_last_agent(client: TestClient) -> Participant:
    client.cookies.clear()  # a new lab participant, not the one this client was
    arrived = client.post("/api/arrivals", json={})
    assert arrived.status_code == 201, arrived.text
    participant = Participant(client, arrived.json()["token"])
    participant.act("/api/participant/consent", agree=True)
    session_id = participant.act("/api/participant/start")["participant"]["current_session_id"]
    demonstrate_each_task(participant, session_id)
    participant.act(f"/api/sessions/{session_id}/finish")
    return participant


def stored_answers(db: Database) -> int:
    with db.read() as s:
        return int(s.scalar(select(func.count()).select_from(QuestionnaireAnswer)) or 0)


def test_the_questionnaire_comes_before_the_completion_code(
    client: TestClient, db: Database
) -> None:
    public = client.get("/api/study").json()["questionnaire"]
    assert [q["id"] for q in public["questions"]] == ["difficulty", "best_agent", "comments"]
    participant = lab_participant_after_the_last_agent(client)
    state = participant.get("/api/participant")
    assert state["status"] == "questionnaire" and state["completion"] is None
    code = client.get("/api/participant/completion", headers=participant.headers)
    assert code.status_code == 409

    def refused(answers: Any, words: str, status: int = 422) -> None:
        before = participant.get("/api/participant")
        response = participant.post("/api/participant/questionnaire", answers=answers)
        assert response.status_code == status, (answers, response.text)
        assert words in response.text, response.text
        after = participant.get("/api/participant")
        assert (after["status"], after["next_seq"]) == (before["status"], before["next_seq"])
        assert stored_answers(db) == 0

    refused({**GOOD, "difficulty": None}, "difficulty")  # not an int or a text
    refused({k: v for k, v in GOOD.items() if k != "difficulty"}, "'difficulty' needs an answer")
    refused({**GOOD, "best_agent": "  "}, "'best_agent' needs an answer")
    refused({**GOOD, "best_agent": "The third agent"}, "takes one of its choices")
    refused({**GOOD, "best_agent": 1}, "takes one of its choices")
    refused({**GOOD, "difficulty": 6}, "1 to 5")
    refused({**GOOD, "difficulty": 0}, "1 to 5")
    refused({**GOOD, "difficulty": "4"}, "1 to 5")
    refused({**GOOD, "difficulty": True}, "difficulty")
    refused({**GOOD, "comments": 3}, "takes text")
    refused({**GOOD, "comments": "x" * 2001}, "at most 2000 characters")
    refused({**GOOD, "comments": "a\x00b"}, "NUL")
    refused({**GOOD, "age": "40"}, "no question 'age'")
    refused([4, "x"], "answers")
    # Shaped as FastAPI's own 422s: the problem, and where it is.
    shaped = participant.post("/api/participant/questionnaire", answers={**GOOD, "difficulty": 9})
    assert shaped.json()["detail"] == [
        {
            "type": "value_error",
            "loc": ["body", "answers", "difficulty"],
            "msg": "question 'difficulty' takes a point of its scale, 1 to 5",
        }
    ]

    # The optional question may be left out; a long answer in any script goes through.
    answers = {"difficulty": 2, "best_agent": "The first agent"}
    done = participant.act("/api/participant/questionnaire", answers=answers)
    assert done["participant"]["status"] == "completed"
    code = done["participant"]["completion"]["code"]
    assert participant.get("/api/participant/completion")["code"] == code
    assert participant.post("/api/participant/questionnaire", answers=GOOD).status_code == 409

    second = lab_participant_after_the_last_agent(client)
    long_text = "é" * 2000  # 4000 bytes of UTF-8, more than any other request may send
    second.act("/api/participant/questionnaire", answers={**GOOD, "comments": long_text})

    with db.read() as s:
        statuses = s.scalars(
            select(StatusChange.status).where(StatusChange.participant_id == 1)
        ).all()
    assert statuses[-3:] == ["teaching", "questionnaire", "completed"]
    tables = export_tables(db)
    rows = tables["questionnaire_answers"]
    assert rows[["participant_id", "question_id", "kind", "answer", "label"]].fillna(
        ""
    ).values.tolist() == [
        [1, "difficulty", "likert", "2", "Hard"],
        [1, "best_agent", "choice", "The first agent", ""],
        [2, "difficulty", "likert", "4", "Easy"],
        [2, "best_agent", "choice", "I could not tell", ""],
        [2, "comments", "text", long_text, ""],
    ]
    assert rows["question"].iloc[0] == "How easy was it to teach the agents?"
    assert tables["participants"]["questionnaire_at"].notna().all()
    described = dictionary_frame()
    described = described[described["file"] == "questionnaire_answers.csv"]
    assert set(rows.columns) <= set(described["column"])


@pytest.mark.parametrize("backend", ["sqlite"], indirect=True)
def test_simulated_participants_answer_the_questionnaire(db: Database, executor: Any) -> None:
    from server.app.main import create_app
    from server.commands.simulated import SimulatedParticipant, TeachingPlan
    from tests.support.server import make_settings

    mturk = parse_study_config(
        example_data(
            learners=["cloning"], tutorial={"enabled": False}, completion={"mode": "mturk"}
        )
    )
    url = db.engine.url.render_as_string(hide_password=False)
    app = create_app(make_settings(url), mturk, db=db, executor=executor)
    plan = TeachingPlan(min_rounds=1, max_rounds=1, agent_try_probability=0.0)
    with TestClient(app) as client:
        run = SimulatedParticipant("http://testserver", 0, 3, plan, client=client).take_part()
    assert run.error is None and run.completed
    rows = export_tables(db)["questionnaire_answers"]
    assert list(rows["question_id"]) == ["difficulty", "best_agent", "comments"]
    assert 1 <= int(rows["answer"].iloc[0]) <= 5
    assert rows["answer"].iloc[1] in mturk.questionnaire.questions[1].choices  # type: ignore[union-attr]


@pytest.mark.parametrize("backend", ["sqlite"], indirect=True)
def test_the_papers_study_has_no_questionnaire(db: Database, executor: Any) -> None:
    """The default study file asks nothing after teaching: the page is told of no
    questionnaire (``/api/study``, the page's study data), and its last agent completes the study (the whole run, status by status,
    is test_flow.py::test_a_whole_run_to_completion_and_submission)."""
    from server.app.main import create_app
    from tests.support.server import make_settings

    default = load_study_config(DEFAULT_STUDY_CONFIG)
    assert default.questionnaire.questions == ()
    url = db.engine.url.render_as_string(hide_password=False)
    app = create_app(make_settings(url), default, db=db, executor=executor)
    with TestClient(app) as client:
        assert client.get("/api/study").json()["questionnaire"] is None


@pytest.mark.parametrize("backend", ["sqlite"], indirect=True)
def test_a_study_without_questions_completes_after_the_last_agent(
    db: Database, executor: Any
) -> None:
    from server.app.main import create_app
    from tests.support.server import make_settings

    plain = parse_study_config(
        {
            **example_data(learners=["cloning"], tutorial={"enabled": False}),
            "questionnaire": {},
        }
    )
    url = db.engine.url.render_as_string(hide_password=False)
    app = create_app(make_settings(url), plain, db=db, executor=executor)
    with TestClient(app) as client:
        assert client.get("/api/study").json()["questionnaire"] is None
        participant = lab_participant_after_the_last_agent(client)
        state = participant.get("/api/participant")
        assert state["status"] == "completed" and state["completion"]["mode"] == "lab"
        refused = participant.post("/api/participant/questionnaire", answers={})
        assert refused.status_code == 409


@pytest.mark.parametrize(
    ("question", "words"),
    [
        ({"kind": "likert", "labels": ["Only one"]}, "at least 2 items"),
        ({"kind": "likert", "labels": ["Same", "Same"]}, "its own, non-empty label"),
        ({"kind": "choice", "choices": ["A", ""]}, "different, non-empty"),
        ({"kind": "choice"}, "choices"),
        ({"kind": "scale", "labels": ["a", "b"]}, "expected tags: 'text', 'likert', 'choice'"),
        ({"labels": ["a", "b"]}, "needs kind = 'text', 'likert' or 'choice'"),
        ({"kind": "text", "id": "Bad Id"}, "id"),
        ({"kind": "text", "options": 3}, "options"),
    ],
)
def test_bad_questions_in_the_study_file_are_reported_with_their_place(
    question: dict[str, Any], words: str
) -> None:
    entry = {"id": "q", "text": "A question?", **question}
    data = example_data(questionnaire={"questions": [entry]})
    with pytest.raises(StudyConfigError, match=r"questionnaire\.questions\.0") as raised:
        parse_study_config(data, "study.toml")
    assert words in str(raised.value)


def test_two_questions_with_one_id_are_refused() -> None:
    twice = {"id": "q", "kind": "text", "text": "Why?"}
    with pytest.raises(StudyConfigError, match="two questions have the same id"):
        parse_study_config(example_data(questionnaire={"questions": [twice, twice]}))


def test_an_answer_sent_with_json_escapes_is_measured_as_text(
    client: TestClient, db: Database
) -> None:
    """Python's json module (and others) write every non-ASCII character as \\u escapes: an
    answer within its length is taken however it was written; the limit still holds."""
    participant = lab_participant_after_the_last_agent(client)
    longest = "\U0001f600" * 2000  # 2000 characters, 8000 bytes of UTF-8, 24000 as escapes
    body = json.dumps({"seq": participant.seq, "answers": {**GOOD, "comments": longest}})
    assert body.isascii() and len(body) > 24_000
    headers = {**participant.headers, "content-type": "application/json"}
    answered = client.post("/api/participant/questionnaire", content=body, headers=headers)
    assert answered.status_code == 200, answered.text
    tables = export_tables(db)
    assert longest in tables["questionnaire_answers"]["answer"].tolist()
    # A body whose text is over the limit is still refused, escaped or not.
    second = lab_participant_after_the_last_agent(client)
    padding = {f"x{number}": "\U0001f600" * 2000 for number in range(3)}
    body = json.dumps({"seq": second.seq, "answers": {**GOOD, **padding}})
    too_large = client.post(
        "/api/participant/questionnaire",
        content=body,
        headers={**second.headers, "content-type": "application/json"},
    )
    assert too_large.status_code == 413, too_large.text
    assert second.get("/api/participant")["status"] == "questionnaire"


def test_an_answer_keyed_by_a_lone_surrogate_is_refused_with_a_message(
    client: TestClient, db: Database
) -> None:
    participant = lab_participant_after_the_last_agent(client)
    for key in ("\\ud800", "\\udfff", "a\\ud800b"):
        body = f'{{"seq": {participant.seq}, "answers": {{"{key}": 1}}}}'
        response = client.post(
            "/api/participant/questionnaire",
            content=body.encode(),
            headers={**participant.headers, "content-type": "application/json"},
        )
        assert response.status_code == 422, response.text
        [problem] = response.json()["detail"]
        assert problem["loc"][:2] == ["body", "answers"] and "no question" in problem["msg"]
    assert participant.get("/api/participant")["status"] == "questionnaire"
    assert stored_answers(db) == 0
