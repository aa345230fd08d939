"""What any visitor may read about the study, and the server's health."""

from __future__ import annotations

from fastapi import APIRouter
from sqlalchemy import text

from server.app.deps import StateDep
from server.app.schemas import PublicStudy

router = APIRouter(prefix="/api", tags=["study"])


@router.get("/study", response_model=PublicStudy)
def read_study(state: StateDep) -> PublicStudy:
    """Title, consent and payment texts, and the shape of the study (no learner names)."""
    return PublicStudy(**state.study.public())


@router.get("/health")
def health(state: StateDep) -> dict[str, object]:
    """The database answers; learner updates waiting or running, done and failed since the
    server started."""
    with state.db.connect() as c:
        c.execute(text("SELECT 1"))
    updates = state.updates
    return {
        "status": "ok",
        "update_backlog": updates.backlog if updates is not None else None,
        "updates_done": updates.completed if updates is not None else None,
        "updates_failed": updates.failed if updates is not None else None,
    }
