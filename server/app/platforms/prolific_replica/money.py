"""The workspace's money: its balance, the study cost calculator, the reward recommendations,
and bonuses (set up, then paid), each with Prolific's fee."""

from __future__ import annotations

import re
from decimal import Decimal, InvalidOperation
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from server.app.platforms.prolific_replica.base import (
    WORKSPACE_ID,
    Refusal,
    Workspace,
    _study,
    new_id,
)
from server.app.platforms.prolific_replica.views import _submissions
from server.app.storage.models import utcnow
from server.app.storage.replica_models import (
    ProlificReplicaBonusSetup,
    ProlificReplicaPayment,
    ProlificReplicaStudy,
    ProlificReplicaSubmission,
)

# Prolific's service fee on rewards and bonuses (VAT: none).
SERVICE_FEE = Decimal("0.333")
# Prolific's minimum hourly pay and the pay it recommends, in cents (researcher help).
HOURLY_REWARD = {"GBP": (600, 900), "USD": (800, 1200)}
# A published study holds the cost of its places not yet paid.
PUBLISHED = ("ACTIVE", "PAUSED", "AWAITING REVIEW")


def with_fees(cents: int) -> int:
    """What paying ``cents`` to participants costs the workspace (Prolific's fee on top)."""
    return cents + int((cents * SERVICE_FEE).to_integral_value())


def balance(s: Session, workspace: Workspace) -> dict[str, Any]:
    """``GET /workspaces/{id}/balance/``: the funds less what was paid (the rewards of approved
    submissions and the bonuses, each with Prolific's fee), and, available, less what the
    published studies hold for their places not yet paid."""
    approved = s.execute(
        select(ProlificReplicaStudy.reward, func.count())
        .join(
            ProlificReplicaSubmission, ProlificReplicaSubmission.study_id == ProlificReplicaStudy.id
        )
        .where(ProlificReplicaSubmission.status == "APPROVED")
        .group_by(ProlificReplicaStudy.id, ProlificReplicaStudy.reward)
    ).all()
    rewards = sum(reward * count for reward, count in approved)
    bonuses = int(s.scalar(select(func.coalesce(func.sum(ProlificReplicaPayment.amount), 0))) or 0)
    total = workspace.funds - with_fees(rewards) - with_fees(bonuses)
    held = 0
    for study in s.scalars(
        select(ProlificReplicaStudy).where(ProlificReplicaStudy.status.in_(PUBLISHED))
    ):
        paid = _submissions(s, study.id, ("APPROVED",))
        held += with_fees(max(study.total_available_places - paid, 0) * study.reward)
    return {
        "currency_code": workspace.currency,
        "total_balance": total,
        "available_balance": total - held,
    }


def study_cost(body: dict[str, Any]) -> tuple[int, Any]:
    """``POST /study-cost-calculator/``: the reward of every place, with Prolific's fee."""
    values = [body.get(name) for name in ("reward", "total_available_places")]
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0 for v in values):
        raise Refusal(400, "reward and total_available_places: positive numbers are required.")
    reward, places = values
    return 200, {"total_cost": with_fees(round(reward * places))}  # type: ignore[operator]


def reward_recommendations(query: dict[str, str]) -> tuple[int, Any]:
    if query.get("workspace_id") != WORKSPACE_ID:
        raise Refusal(400, "workspace_id: the id of your workspace is required.")
    currency = query.get("currency")
    if currency not in HOURLY_REWARD:
        raise Refusal(400, "currency: one of GBP, USD.")
    least, good = HOURLY_REWARD[currency]
    return 200, [
        {"currency": currency, "min_reward_per_hour": least, "recommended_reward_per_hour": good}
    ]


def _cents(text: str) -> int:
    if not re.fullmatch(r"[0-9]+(\.[0-9]{1,2})?", text):
        raise Refusal(400, f"csv_bonuses: {text!r} is not an amount.")
    try:
        return int(Decimal(text) * 100)
    except InvalidOperation:  # pragma: no cover - the pattern above
        raise Refusal(400, f"csv_bonuses: {text!r} is not an amount.") from None


def set_up_bonuses(s: Session, body: dict[str, Any]) -> tuple[int, Any]:
    study_id = body.get("study_id")
    csv = body.get("csv_bonuses")
    if not isinstance(study_id, str) or not isinstance(csv, str) or not csv.strip():
        raise Refusal(400, "study_id and csv_bonuses are required.")
    _study(s, study_id)
    total = 0
    for line in csv.strip().splitlines():
        who, _, amount = line.partition(",")
        cents = _cents(amount.strip())
        if cents <= 0:
            raise Refusal(400, f"csv_bonuses: the amount for {who} must be more than 0.")
        taken = s.scalar(
            select(ProlificReplicaSubmission).where(
                ProlificReplicaSubmission.study_id == study_id,
                (ProlificReplicaSubmission.participant_id == who.strip())
                | (ProlificReplicaSubmission.id == who.strip()),
            )
        )
        if taken is None:
            raise Refusal(400, f"csv_bonuses: {who.strip()} did not take part in this study.")
        total += cents
    setup = ProlificReplicaBonusSetup(
        id=new_id(), study_id=study_id, csv_bonuses=csv, amount=total, created_at=utcnow()
    )
    s.add(setup)
    fees = with_fees(total) - total
    return 201, {
        "id": setup.id,
        "study": study_id,
        "amount": total,
        "fees": fees,
        "vat": 0,
        "total_amount": total + fees,
    }


def pay_bonuses(s: Session, setup_id: str) -> tuple[int, Any]:
    setup = s.get(ProlificReplicaBonusSetup, setup_id)
    if setup is None:
        raise Refusal(404, f"Bulk bonus payment {setup_id} not found.")
    now = utcnow()
    for line in setup.csv_bonuses.strip().splitlines():
        who, _, amount = line.partition(",")
        participant = who.strip()
        submission = s.get(ProlificReplicaSubmission, participant)
        if submission is not None:
            participant = submission.participant_id
        s.add(
            ProlificReplicaPayment(
                setup_id=setup.id,
                participant_id=participant,
                amount=_cents(amount.strip()),
                paid_at=now,
            )
        )
    return 202, None
