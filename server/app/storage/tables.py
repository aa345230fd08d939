"""The Core table handles of the study's ORM models (``models``), made once, for the statements
of the request path (``records``) and the code that writes SQL of its own.
"""

from __future__ import annotations

from server.app.storage.models import (
    AttentionCheck,
    Episode,
    Erasure,
    Event,
    LearnerUpdate,
    LearningSession,
    Participant,
    ParticipantToken,
    QuestionnaireAnswer,
    StatusChange,
)
from server.app.storage.records import table_of

PARTICIPANTS = table_of(Participant)
SESSIONS = table_of(LearningSession)
EPISODES = table_of(Episode)
EVENTS = table_of(Event)
UPDATES = table_of(LearnerUpdate)
STATUS_CHANGES = table_of(StatusChange)
TOKENS = table_of(ParticipantToken)
ANSWERS = table_of(QuestionnaireAnswer)
CHECKS = table_of(AttentionCheck)
ERASURES = table_of(Erasure)
