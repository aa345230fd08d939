"""A participant's withdrawal from the study page ("stop and delete my data"): their data is
erased (``erasure.erase``, by the participant) and the page is told how to leave the platform
(``Platform.withdrawal``)."""

from __future__ import annotations

from pydantic import BaseModel, Field

from server.app import platform_registry as registry
from server.app.participants.tokens import participant_for
from server.app.platform_registry import PlatformName
from server.app.rights.erasure import erase, installation_secret
from server.app.storage.db import Database
from server.app.storage.vocabulary import ErasedBy
from server.app.study_file import StudyConfig


class Withdrawal(BaseModel):
    """What the page shows (and where it sends the participant) after a withdrawal."""

    platform: PlatformName
    message: str
    redirect_url: str | None = Field(
        None,
        description="Prolific with a NO_CONSENT code: the page's link back to Prolific (the "
        "code's completion URL, where Prolific asks the participant to return the submission).",
    )


def withdraw(db: Database, token: str | None, study: StudyConfig, secret: str | None) -> Withdrawal:
    """Erase the token's participant (401 for an unknown token: nothing to erase)."""
    with db.transaction() as c:
        participant = participant_for(c, token, lock=not db.is_sqlite)
        erase(c, participant.id, ErasedBy.PARTICIPANT, installation_secret(c, secret))
    db.forget_removed()
    leaving = registry.platform(participant.platform).withdrawal(participant, study)
    return Withdrawal(
        platform=participant.platform, message=leaving.message, redirect_url=leaving.redirect_url
    )
