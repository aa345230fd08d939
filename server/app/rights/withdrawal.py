"""A participant's withdrawal from the study page ("stop and delete my data"): their data is
erased (``erasure.erase``, by the participant) and the page is told how to leave the platform."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field

from server.app.config import StudyConfig
from server.app.participants.completion import prolific_exit
from server.app.participants.tokens import participant_for
from server.app.rights.erasure import erase, installation_secret
from server.app.storage.db import Database

MTURK_RETURN = (
    "Your data has been deleted. To leave this HIT, press \u201cReturn\u201d on Mechanical "
    "Turk\u2019s page (above this study, or in your list of HITs): returning a HIT does not "
    "count against you."
)
PROLIFIC_RETURN = (
    "Your data has been deleted. Please return your submission on Prolific (\u201cReturn\u201d "
    "on the study\u2019s page there), so that you are not counted as having taken part."
)
LAB_DONE = "Your data has been deleted. You may close this page."


class Withdrawal(BaseModel):
    """What the page shows (and where it sends the participant) after a withdrawal."""

    platform: Literal["mturk", "prolific", "lab"]
    message: str
    redirect_url: str | None = Field(
        None, description="Prolific with a NO_CONSENT code: send the participant here."
    )


def withdraw(db: Database, token: str | None, study: StudyConfig, secret: str | None) -> Withdrawal:
    """Erase the token's participant (401 for an unknown token: nothing to erase)."""
    with db.transaction() as c:
        participant = participant_for(c, token, lock=not db.is_sqlite)
        erase(c, participant.id, "participant", installation_secret(c, secret))
    db.forget_removed()
    platform = participant.platform
    if platform == "mturk":
        return Withdrawal(platform="mturk", message=MTURK_RETURN)
    if platform == "prolific":
        code = study.completion.prolific_no_consent_code
        if code is None:
            return Withdrawal(platform="prolific", message=PROLIFIC_RETURN)
        return Withdrawal(
            platform="prolific",
            message="Your data has been deleted. Taking you back to Prolific\u2026",
            redirect_url=prolific_exit(participant, study, code),
        )
    return Withdrawal(platform="lab", message=LAB_DONE)
