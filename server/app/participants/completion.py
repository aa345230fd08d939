"""The tutorial's steps, the questionnaire and completion: the completion code and where the
participant goes at the end.
"""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

from server.app import platform_registry as registry
from server.app.errors import ApiError, InvalidInput
from server.app.participants import tokens
from server.app.participants.statuses import set_status
from server.app.participants.tokens import CODE_ALPHABET
from server.app.participants.transaction import Transaction
from server.app.schemas import (
    Completion,
)
from server.app.storage.records import add
from server.app.storage.tables import ANSWERS
from server.app.storage.vocabulary import FINISHED_STATUSES, ParticipantStatus
from server.app.study_file import LikertQuestion, Question, StudyConfig, TextQuestion


def answer_questionnaire(transaction: Transaction, answers: dict[str, int | str]) -> None:
    """Store the answers to the post-study questionnaire (all of them valid, every required
    question answered: 422 otherwise, nothing stored), then the participant has completed."""
    status = transaction.participant.status
    if status != ParticipantStatus.QUESTIONNAIRE:
        raise ApiError(409, f"the questionnaire is not being answered now (status {status})")
    questions = {question.id: question for question in transaction.study.questionnaire.questions}
    unknown = sorted(set(answers) - set(questions))
    if unknown:
        raise InvalidInput(
            ("body", "answers", unknown[0]),
            f"no question {', '.join(map(repr, unknown))} in this questionnaire",
        )
    rows = []
    for question_id, question in questions.items():
        value = answers.get(question_id)
        if isinstance(value, str) and not value.strip():
            value = None
        if value is None:
            if question.required:
                raise InvalidInput(
                    ("body", "answers", question_id), f"question {question_id!r} needs an answer"
                )
            continue
        rows.append(
            {
                "participant_id": transaction.participant.id,
                "question_id": question_id,
                "kind": question.kind,
                "question": question.text,
                "answered_at": transaction.now,
                **checked_answer(question, value),
            }
        )
    for row in rows:
        add(transaction.c, ANSWERS, **row)
    complete(transaction)


def checked_answer(question: Question, value: int | str) -> dict[str, str | None]:
    """The answer's ``answer`` and ``label`` columns; 422 for an answer the question does not
    take."""
    loc = ("body", "answers", question.id)
    where = f"question {question.id!r}"
    if isinstance(question, TextQuestion):
        if not isinstance(value, str):
            raise InvalidInput(loc, f"{where} takes text")
        if len(value) > question.max_length:
            raise InvalidInput(loc, f"{where}: at most {question.max_length} characters")
        return {"answer": value, "label": None}
    if isinstance(question, LikertQuestion):
        points = len(question.labels)
        if not isinstance(value, int) or not 1 <= value <= points:
            raise InvalidInput(loc, f"{where} takes a point of its scale, 1 to {points}")
        return {"answer": str(value), "label": question.labels[value - 1]}
    if not isinstance(value, str) or value not in question.choices:
        raise InvalidInput(
            loc, f"{where} takes one of its choices: {', '.join(map(repr, question.choices))}"
        )
    return {"answer": value, "label": None}


def complete(transaction: Transaction) -> None:
    """The participant has completed, with the study's code on their platform (Prolific's) or
    a random one."""
    participant = transaction.participant
    fixed = registry.platform(participant.platform).fixed_code(transaction.study)
    participant.completion_code = fixed or "".join(
        tokens.SYSTEM_RANDOM.choice(CODE_ALPHABET) for _ in range(10)
    )
    set_status(transaction.c, participant, ParticipantStatus.COMPLETED, transaction.now)


def reach_tutorial_step(transaction: Transaction, step: int) -> None:
    """The page's tutorial reached ``step``; the step kept never goes back (another tab may be
    behind)."""
    participant = transaction.participant
    if participant.status != ParticipantStatus.TUTORIAL:
        raise ApiError(409, f"the tutorial is not in progress (status {participant.status})")
    participant.tutorial_step = max(int(participant.tutorial_step), step)


def submission(transaction: Transaction) -> None:
    """The page reports that it sends the participant's submission to the platform."""
    status = transaction.participant.status
    if status == ParticipantStatus.SUBMITTED:
        raise ApiError(409, "the submission was already recorded")
    if status != ParticipantStatus.COMPLETED:
        raise ApiError(409, f"the study is not completed yet (status {status})")
    set_status(transaction.c, transaction.participant, ParticipantStatus.SUBMITTED, transaction.now)


def completion(participant: Any, study: StudyConfig) -> Completion | None:
    """The completion code and how to hand it in (the platform says: ``Platform.handing``); None
    until the completion is committed. A participant who declined consent goes back with the
    platform's no-consent code, if it has one (Prolific's NO_CONSENT); one turned away by the
    device check, with its code for that (Prolific's INCOMPATIBLE_DEVICE)."""
    platform = registry.platform(participant.platform)
    code = None
    if participant.status == ParticipantStatus.DECLINED:
        code = platform.no_consent_code(study)
    elif participant.status == ParticipantStatus.INCOMPATIBLE:
        code = platform.incompatible_device_code(study)
    if code is None and participant.status in FINISHED_STATUSES:
        code = participant.completion_code
    if code is None:
        return None
    handing = platform.handing(participant, study, code)
    return Completion(code=code, mode=platform.name, **asdict(handing))


# -- views ----------------------------------------------------------------------------------
