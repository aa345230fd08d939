"""The string vocabularies (``storage/vocabulary.py``): the strings the database stores, the API
lists and the export writes are the ones below, so that a vocabulary that drifts (a member
renamed, added or dropped, a literal of the API that forgets a member) fails here."""

from __future__ import annotations

from enum import StrEnum
from typing import Any, get_args

import pytest
from pydantic import TypeAdapter, ValidationError
from sqlalchemy import select, text

from server.app import schemas
from server.app.export.columns import PARTICIPANTS as PARTICIPANT_COLUMNS
from server.app.export.columns import STATUS_COLUMNS
from server.app.storage import vocabulary as v
from server.app.storage.db import Database
from server.app.storage.records import add
from server.app.storage.tables import EPISODES, EVENTS, PARTICIPANTS, SESSIONS

# The values stored in the database, in the vocabularies' order. Changing one of these is
# changing the data (an export or an analysis of an earlier study reads the old strings).
STORED = {
    v.ParticipantStatus: [
        "waiting",
        "arrived",
        "incompatible",
        "consented",
        "declined",
        "tutorial",
        "teaching",
        "questionnaire",
        "completed",
        "submitted",
        "returned",
        "abandoned",
    ],
    v.ExclusionMark: ["excluded", "included"],
    v.SessionKind: ["tutorial", "study"],
    v.SessionStatus: ["pending", "active", "finished"],
    v.Mode: ["idle", "demonstrate", "agent"],
    v.LastAction: ["demonstration", "agent", "idle"],
    v.EpisodeKind: ["demonstration", "agent"],
    v.EpisodeEnd: ["end", "goal", "horizon", "task", "mode", "reset", "finish"],
    v.Observed: ["demonstration", "agent_step", "transition", "feedback"],
    v.UpdateStatus: ["pending", "done", "failed"],
    v.CheckStatus: ["pending", "active", "passed", "failed"],
    v.ReviewDecision: ["approved", "rejected"],
    v.ReviewState: ["pending", "done"],
    v.BonusState: ["pending", "in_doubt", "set_up", "paying", "paid"],
    v.ErasedBy: ["participant", "experimenter"],
    v.ReplicaAssignmentStatus: ["accepted", "returned", "submitted", "approved", "rejected"],
}

# The API's literals and the members each lists (all of its vocabulary but where noted).
LITERALS: dict[Any, list[StrEnum]] = {
    schemas.Mode: list(v.Mode),
    schemas.SessionKind: list(v.SessionKind),
    schemas.SessionStatus: list(v.SessionStatus),
    schemas.EpisodeKind: list(v.EpisodeKind),
    # The page is shown the check being taken or its outcome, never a pending one.
    schemas.CheckShown: [s for s in v.CheckStatus if s is not v.CheckStatus.PENDING],
    schemas.ReviewDecision: list(v.ReviewDecision),
    schemas.ReviewState: list(v.ReviewState),
}


def vocabularies() -> list[type[StrEnum]]:
    return [
        value
        for value in vars(v).values()
        if isinstance(value, type) and issubclass(value, v.Vocabulary) and value is not v.Vocabulary
    ]


def test_every_vocabulary_stores_the_strings_listed_here() -> None:
    assert set(vocabularies()) == set(STORED)
    for vocabulary, strings in STORED.items():
        assert [member.value for member in vocabulary] == strings, vocabulary.__name__
        for member in vocabulary:
            # The member is its string: rows read back compare equal, and text shows the string.
            assert member == member.value and f"{member}" == member.value
            assert repr(member) == repr(member.value)
            assert hash(member) == hash(member.value)


def test_the_flow_statuses_are_in_the_vocabulary_s_order() -> None:
    order = list(v.ParticipantStatus)
    assert list(v.FLOW_STATUSES) == sorted(v.FLOW_STATUSES, key=order.index)
    assert set(v.IN_PROGRESS) < set(v.FLOW_STATUSES)
    assert set(v.FINISHED_STATUSES) == set(v.FLOW_STATUSES) - set(v.IN_PROGRESS)
    assert v.ParticipantStatus.WAITING not in v.FLOW_STATUSES


@pytest.mark.parametrize("literal", list(LITERALS), ids=lambda x: str(x))
def test_the_api_s_literals_list_their_vocabulary(literal: Any) -> None:
    assert list(get_args(literal)) == LITERALS[literal]
    # The JSON schema (OpenAPI) lists the strings, as a literal of strings would.
    assert TypeAdapter(literal).json_schema() == {
        "enum": [member.value for member in LITERALS[literal]],
        "type": "string",
    }


def test_a_mode_outside_the_vocabulary_is_refused_with_its_strings_listed() -> None:
    assert schemas.ModeRequest.model_validate({"seq": 1, "mode": "demonstrate"}).mode is (
        v.Mode.DEMONSTRATE
    )
    with pytest.raises(ValidationError) as refused:
        schemas.ModeRequest.model_validate({"seq": 1, "mode": "watch"})
    [error] = refused.value.errors()
    assert error["msg"] == "Input should be 'idle', 'demonstrate' or 'agent'"


def test_the_export_has_a_first_time_column_for_every_status_but_waiting() -> None:
    names = [column.name for column in PARTICIPANT_COLUMNS]
    assert [f"{status}_at" for status in STATUS_COLUMNS] == [
        name
        for name in names
        if name.endswith("_at") and name.removesuffix("_at") in set(v.ParticipantStatus)
    ]
    assert set(STATUS_COLUMNS) == set(v.ParticipantStatus) - {v.ParticipantStatus.WAITING}


def test_members_are_stored_as_their_strings(db: Database) -> None:
    with db.transaction() as c:
        participant_id = add(
            c,
            PARTICIPANTS,
            token_hash="b" * 64,
            platform="lab",
            status=v.ParticipantStatus.QUESTIONNAIRE,
        )
        session_id = add(
            c,
            SESSIONS,
            participant_id=participant_id,
            ordinal=0,
            kind=v.SessionKind.TUTORIAL,
            domain="navigation",
            environment="doorway",
            learner="bam",
            colour_name="orange",
            colour_hex="#E69F00",
            seed=7,
            demonstrated=[],
        )
        add(
            c,
            EPISODES,
            session_id=session_id,
            index=0,
            kind=v.EpisodeKind.AGENT,
            task=0,
            start_state=0,
            end_reason=v.EpisodeEnd.HORIZON,
        )
        add(
            c,
            EVENTS,
            participant_id=participant_id,
            session_id=session_id,
            seq=1,
            kind="move",
            mode=v.Mode.IDLE,
            record=v.Observed.IDLE_MOVE,
            request_hash="f" * 64,
            response="{}",
        )
    with db.connect() as c:
        # As another reader of the database sees them: plain text.
        raw = c.execute(
            text(
                "SELECT p.status, s.kind, s.status, s.mode, e.kind, e.end_reason, v.mode, "
                "v.record FROM participants p JOIN learning_sessions s ON s.participant_id = p.id "
                "JOIN episodes e ON e.session_id = s.id JOIN events v ON v.session_id = s.id"
            )
        ).one()
        assert tuple(raw) == (
            "questionnaire",
            "tutorial",
            "pending",  # the column defaults are members too
            "idle",
            "agent",
            "horizon",
            "idle",
            "transition",
        )
        assert all(type(value) is str for value in raw)
        status = c.scalar(select(PARTICIPANTS.c.status))
        assert status == v.ParticipantStatus.QUESTIONNAIRE
