"""Review of submitted work: approve or reject a participant's submission, and pay a bonus,
on the participant's platform (MTurk or Prolific, or the local replica of either), with every
money action carried out exactly once.

The platform's side is one interface, ``ReviewBackend``. The study's side is here, and it is
the same for every platform:

1. the request is checked (the participant submitted work on the backend's platform; the amount
   is a plain decimal with at most two places; message is plain text);
2. the intent is recorded in the database *before* the platform is called: a decision as a
   ``pending`` row of ``reviews``, a bonus as a ``pending`` row of ``bonuses`` with
   its request token (sent as MTurk's UniqueRequestToken). On Prolific, whose ``pay`` call is
   not idempotent, the bonus's set-up id is stored (``set_up``) before ``pay`` is called, and
   ``pay`` is called only by the request that moved the row from ``set_up`` to ``paying``;
3. the platform is called, and the row is settled (``done``, ``paid``).

A retry, a double click or a second tab with the same request finds the row: a settled one is
answered as it stands; an unsettled one (the platform failed, or the server died between the
call and the record) is reconciled from the platform: MTurk answers "already exists" for a
UniqueRequestToken it has paid, and a decision already taken shows in the submission's status.
A definite refusal by the platform removes the intent (nothing was done there).

A Prolific bonus whose ``pay`` was sent and not answered 2xx (a 429, a time-out, a 5xx, a
refusal, or the server dying while it was out) may have been paid: it is ``in_doubt``, and only
Prolific's record settles it. The submission's ``bonus_payments`` (GET /submissions/{id}/) lists
the bonuses paid on it: a bonus it lists is ``paid``; one it does not list, once Prolific has had
``PAY_SETTLES_WITHIN`` to carry out an asynchronous pay, was not paid, goes back to ``set_up``
and is paid again, once. A resend of the bonus (same token) or the reconciliation settles it;
until then no new bonus for that participant is taken, so that a fresh form cannot pay it twice.

The decisions are in ``decisions``, the bonuses in ``bonuses``, what they share in ``base``;
every name is imported from here.
"""

from __future__ import annotations

from server.app.platforms.review.base import (
    AMOUNT,
    CONTROL,
    MAX_BONUS,
    PROLIFIC_MIN_MESSAGE,
    REJECTION_CATEGORIES,
    SETTLE_WAIT_SECONDS,
    AlreadyDone,
    RejectionCategory,
    ReviewBackend,
    Reviewed,
    ReviewRefused,
    ReviewUnavailable,
    dollars,
    message_text,
    money,
    parse_amount,
    reviewable,
)
from server.app.platforms.review.bonuses import (
    PAY_CALL_LIMIT,
    PAY_SETTLES_WITHIN,
    TOKEN_MARGIN,
    UNSETTLED,
    bonus_note,
    pay_bonus,
    reconcile_bonuses,
)
from server.app.platforms.review.decisions import (
    review_submission,
)

__all__ = [
    "AMOUNT",
    "CONTROL",
    "MAX_BONUS",
    "PAY_CALL_LIMIT",
    "PAY_SETTLES_WITHIN",
    "PROLIFIC_MIN_MESSAGE",
    "REJECTION_CATEGORIES",
    "SETTLE_WAIT_SECONDS",
    "TOKEN_MARGIN",
    "UNSETTLED",
    "AlreadyDone",
    "RejectionCategory",
    "ReviewBackend",
    "ReviewRefused",
    "ReviewUnavailable",
    "Reviewed",
    "bonus_note",
    "dollars",
    "message_text",
    "money",
    "parse_amount",
    "pay_bonus",
    "reconcile_bonuses",
    "review_submission",
    "reviewable",
]
