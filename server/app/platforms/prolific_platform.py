"""Prolific as a platform (``PROLIFIC``): participants arrive with PROLIFIC_PID, STUDY_ID and
SESSION_ID, finish with the study's completion code by a redirect to ``prolific_url`` (or to the
replica, for a study of this server's Prolific replica), and leave with the NO_CONSENT code when
they decline or withdraw; a rejection follows Prolific's rules; Prolific's status of the
submission is kept (``prolific_sync``, and after each decision)."""

from __future__ import annotations

from datetime import datetime, timedelta
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
    workspace_of,
)
from server.app.platforms.review import PROLIFIC_MIN_MESSAGE
from server.app.storage.records import table_of
from server.app.storage.replica_models import (
    ProlificReplicaBonusSetup,
    ProlificReplicaGroupMember,
    ProlificReplicaMessage,
    ProlificReplicaPayment,
    ProlificReplicaSubmission,
)
from server.app.storage.vocabulary import ReviewDecision

if TYPE_CHECKING:
    from server.app.settings import Settings
    from server.app.storage.db import Database
    from server.app.study_file import StudyConfig

# Prolific approves, and pays, a submission still AWAITING REVIEW this long after it was
# completed: "Submissions that are awaiting review are automatically approved after 21 days"
# (docs.prolific.com/api-reference/submissions/submissions-guide); "After a participant completes
# a study, submissions move to Awaiting Review, where you have up to 21 days to review the
# submission" (researcher-help.prolific.com/en/article/e55aad, "Submission statuses explained").
AUTO_APPROVAL = timedelta(days=21)

PROLIFIC_SUBMISSIONS = table_of(ProlificReplicaSubmission)
PROLIFIC_PAYMENTS = table_of(ProlificReplicaPayment)
PROLIFIC_BONUS_SETUPS = table_of(ProlificReplicaBonusSetup)
PROLIFIC_MESSAGES = table_of(ProlificReplicaMessage)
PROLIFIC_GROUP_MEMBERS = table_of(ProlificReplicaGroupMember)


class Prolific(BasePlatform):
    name = "prolific"
    display_name = "Prolific"
    parameters = {"PROLIFIC_PID": ID_PATTERN, "STUDY_ID": ID_PATTERN, "SESSION_ID": ID_PATTERN}
    ids = {
        "platform_participant_id": "PROLIFIC_PID",
        "platform_submission_id": "SESSION_ID",
        "platform_study_id": "STUDY_ID",
    }
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
        if ids.platform_study_id is not None and is_replica_study(c, ids.platform_study_id):
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

    def incompatible_device_code(self, study: StudyConfig) -> str | None:
        return study.completion.prolific_incompatible_device_code

    def withdrawal(self, participant: Any, study: StudyConfig) -> Leaving:
        code = self.no_consent_code(study)
        if code is None:
            return Leaving(self.done)
        # Our page says what happened; its link takes the NO_CONSENT code to Prolific's
        # completion URL, where the code's REQUEST_RETURN asks the participant to return.
        return Leaving(
            "Your data has been deleted. Your submission stays on Prolific until you return it: "
            "go back to Prolific with the button below, where you are asked to return it, and "
            "press \u201cReturn\u201d there, so that you are not counted as having taken part.",
            self.handing(participant, study, code).redirect_url,
        )

    def review_backend(self, settings: Settings, db: Database, replica: bool) -> ProlificBackend:
        if replica:
            # Prolific's client, answered by the replica inside the server.
            token = settings.admin_token.get_secret_value() if settings.admin_token else ""
            client = ProlificClient(
                "http://replica/prolific/api/v1",
                token,
                transport=ReplicaTransport(db, token, workspace=workspace_of(settings)),
            )
            return ProlificBackend(client, settings.prolific_currency, name="prolific-replica")
        if settings.prolific_token is None:
            raise ApiError(503, "BAM_REVIEW_BACKEND=prolific needs BAM_PROLIFIC_TOKEN")
        client = ProlificClient(
            settings.prolific_api_url, settings.prolific_token.get_secret_value()
        )
        return ProlificBackend(client, settings.prolific_currency)

    def awaits_decision(self, participant: Any) -> bool:
        """Submitted work, and two more that Prolific pays unless the researcher decides: a
        participant who declined consent, whose NO_CONSENT code completed the submission
        (AWAITING REVIEW, approved by itself after 21 days unless they return it), and one who
        finished although their submission timed out (Prolific lets a timed-out submission be
        approved) or whose code reached Prolific before our page said it was sent. Not a
        submission the participant returned ("Return and cancel reward"): Prolific would pay it
        only as an extra participant."""
        status, prolific = participant.status, participant.platform_status
        if prolific == "RETURNED":
            return False
        if status == "declined":
            return bool(prolific == "AWAITING REVIEW")
        if status == "completed":
            return prolific in ("AWAITING REVIEW", "TIMED-OUT")
        return bool(status == "submitted")

    def auto_approval_at(self, participant: Any) -> datetime | None:
        """21 days after Prolific completed the submission, while it is AWAITING REVIEW."""
        completed = participant.platform_completed_at
        if participant.platform_status != "AWAITING REVIEW" or completed is None:
            return None
        return completed + AUTO_APPROVAL  # type: ignore[no-any-return]

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

    def bonus_budget_cents(self, study: StudyConfig) -> int | None:
        budget = study.prolific.bonus_budget if study.prolific is not None else None
        return None if budget is None else int(budget * 100)

    def own_replica_rows(self, participant: Any) -> Rows:
        worker, submission = participant.platform_participant_id, participant.platform_submission_id
        if not worker or not submission:
            return []
        setups = select(PROLIFIC_BONUS_SETUPS.c.id).where(
            PROLIFIC_BONUS_SETUPS.c.study_id == participant.platform_study_id
        )
        payments, submissions = PROLIFIC_PAYMENTS.c, PROLIFIC_SUBMISSIONS.c
        messages = PROLIFIC_MESSAGES.c
        return [
            (PROLIFIC_PAYMENTS, and_(payments.participant_id == worker, payments.setup_id.in_(setups))),
            (
                PROLIFIC_MESSAGES,
                and_(
                    messages.recipient_id == worker,
                    messages.study_id == participant.platform_study_id,
                ),
            ),
            (PROLIFIC_SUBMISSIONS, and_(submissions.id == submission, submissions.participant_id == worker)),
            (PROLIFIC_GROUP_MEMBERS, PROLIFIC_GROUP_MEMBERS.c.participant_id == worker),
        ]  # fmt: skip

    def shared_replica_rows(self, participant: Any) -> Rows:
        """A bonus set-up's CSV, one line per participant of the study."""
        if participant.platform_participant_id and participant.platform_study_id:
            return [
                (
                    PROLIFIC_BONUS_SETUPS,
                    PROLIFIC_BONUS_SETUPS.c.study_id == participant.platform_study_id,
                )
            ]
        return []


PROLIFIC = Prolific()
