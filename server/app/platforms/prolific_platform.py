"""Prolific as a platform (``PROLIFIC``): participants arrive with PROLIFIC_PID, STUDY_ID and
SESSION_ID, finish with the study's completion code by a redirect to ``prolific_url`` (or to the
replica, for a study of this server's Prolific replica), and leave with the NO_CONSENT code when
they decline or withdraw; a rejection follows Prolific's rules; Prolific's status of the
submission is kept (``prolific_sync``, and after each decision)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from sqlalchemy import Connection, and_, select

from server.app.errors import ApiError, InvalidInput
from server.app.platforms.base import (
    ID_PATTERN,
    ArrivalIds,
    BasePlatform,
    Handing,
    Leaving,
    Released,
    Rows,
)
from server.app.platforms.prolific import ProlificBackend, ProlificClient
from server.app.platforms.prolific_replica import (
    REPLICA_PATH,
    ReplicaTransport,
    completion_url,
    is_replica_study,
)
from server.app.platforms.review import PROLIFIC_MIN_MESSAGE
from server.app.storage.records import table_of
from server.app.storage.replica_models import (
    ProlificReplicaBonusSetup,
    ProlificReplicaPayment,
    ProlificReplicaSubmission,
)
from server.app.storage.vocabulary import ReviewDecision

if TYPE_CHECKING:
    from server.app.config import StudyConfig
    from server.app.settings import Settings
    from server.app.storage.db import Database

PROLIFIC_SUBMISSIONS = table_of(ProlificReplicaSubmission)
PROLIFIC_PAYMENTS = table_of(ProlificReplicaPayment)
PROLIFIC_BONUS_SETUPS = table_of(ProlificReplicaBonusSetup)


class Prolific(BasePlatform):
    name = "prolific"
    display_name = "Prolific"
    parameters = {"PROLIFIC_PID": ID_PATTERN, "STUDY_ID": ID_PATTERN, "SESSION_ID": ID_PATTERN}
    ids = {"worker_id": "PROLIFIC_PID", "assignment_id": "SESSION_ID", "hit_id": "STUDY_ID"}
    reviews = True
    done = (
        "Your data has been deleted. Please return your submission on Prolific (\u201cReturn\u201d "
        "on the study\u2019s page there), so that you are not counted as having taken part."
    )
    # Released on Prolific's word (RETURNED or TIMED-OUT): the place went to another.
    released = Released(
        "This study has ended for you",
        "Prolific shows that this study was returned or that its time ran out, so your place has "
        "gone to another participant and it cannot be continued. What you did is kept. Thank "
        "you for your interest.",
        "Prolific shows that this study was returned or that its time ran out: your place has "
        "gone to another participant, and this session has ended",
    )

    def submit_to(self, c: Connection, ids: ArrivalIds) -> str | None:
        # A study of this server's Prolific replica: the participant goes back to it.
        if ids.hit_id is not None and is_replica_study(c, ids.hit_id):
            return REPLICA_PATH
        return None

    def fixed_code(self, study: StudyConfig) -> str | None:
        return study.completion.prolific_code if study.completion.mode == self.name else None

    def handing(self, participant: Any, study: StudyConfig, code: str) -> Handing:
        """A redirect to the study's ``prolific_url``, or, for a participant of this server's
        Prolific replica, to the replica's completion URL."""
        if participant.submit_to == REPLICA_PATH:
            return Handing(redirect_url=completion_url(code))
        return Handing(redirect_url=study.completion.prolific_redirect(code))

    def no_consent_code(self, study: StudyConfig) -> str | None:
        return study.completion.prolific_no_consent_code

    def withdrawal(self, participant: Any, study: StudyConfig) -> Leaving:
        code = self.no_consent_code(study)
        if code is None:
            return Leaving(self.done)
        return Leaving(
            "Your data has been deleted. Taking you back to Prolific\u2026",
            self.handing(participant, study, code).redirect_url,
        )

    def review_backend(self, settings: Settings, db: Database, replica: bool) -> ProlificBackend:
        if replica:
            # Prolific's client, answered by the replica inside the server.
            token = settings.admin_token.get_secret_value() if settings.admin_token else ""
            client = ProlificClient(
                "http://replica/prolific/api/v1", token, transport=ReplicaTransport(db, token)
            )
            return ProlificBackend(client, settings.prolific_currency, name="prolific-replica")
        if settings.prolific_token is None:
            raise ApiError(503, "BAM_REVIEW_BACKEND=prolific needs BAM_PROLIFIC_TOKEN")
        client = ProlificClient(
            settings.prolific_api_url, settings.prolific_token.get_secret_value()
        )
        return ProlificBackend(client, settings.prolific_currency)

    def check_rejection(self, message: str | None, category: str | None) -> None:
        # Prolific's own rules, checked here first (Prolific answers 400).
        if len((message or "").strip()) < PROLIFIC_MIN_MESSAGE:
            raise InvalidInput(
                ("body", "message"),
                f"a rejection on Prolific needs a message of at least {PROLIFIC_MIN_MESSAGE} "
                "characters that tells the participant why",
            )
        if category is None:
            raise InvalidInput(
                ("body", "rejection_category"),
                "a rejection on Prolific needs one of Prolific's rejection categories",
            )

    def status_after(self, decision: ReviewDecision) -> str | None:
        # Prolific's status of the submission is now ours (its webhook says it again).
        return "APPROVED" if decision == ReviewDecision.APPROVED else "REJECTED"

    def own_replica_rows(self, participant: Any) -> Rows:
        worker, submission = participant.worker_id, participant.assignment_id
        if not worker or not submission:
            return []
        setups = select(PROLIFIC_BONUS_SETUPS.c.id).where(
            PROLIFIC_BONUS_SETUPS.c.study_id == participant.hit_id
        )
        payments, submissions = PROLIFIC_PAYMENTS.c, PROLIFIC_SUBMISSIONS.c
        return [
            (PROLIFIC_PAYMENTS, and_(payments.participant_id == worker, payments.setup_id.in_(setups))),
            (PROLIFIC_SUBMISSIONS, and_(submissions.id == submission, submissions.participant_id == worker)),
        ]  # fmt: skip

    def shared_replica_rows(self, participant: Any) -> Rows:
        """A bonus set-up's CSV, one line per participant of the study."""
        if participant.worker_id and participant.hit_id:
            return [(PROLIFIC_BONUS_SETUPS, PROLIFIC_BONUS_SETUPS.c.study_id == participant.hit_id)]
        return []


PROLIFIC = Prolific()
