"""What any visitor may read about the study, and the server's health."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse
from sqlalchemy import text

from server.app.deps import StateDep
from server.app.schemas import PublicStudy

router = APIRouter(prefix="/api", tags=["study"])


@router.get("/study", response_model=PublicStudy)
def read_study(state: StateDep) -> PublicStudy:
    """Title, consent and payment texts, and the shape of the study (no learner names)."""
    return PublicStudy(**state.study.public())


@router.get("/health")
def health(state: StateDep) -> JSONResponse:
    """Ready (200) once the database answers and every learner-update process (with
    ``BAM_UPDATE_SCHEDULER``: every thread of the Dask cluster's workers) has loaded the
    learners' compiled kernels; 503 before (starting). With the updates waiting or running,
    done and failed since the server started."""
    with state.db.connect() as c:
        c.execute(text("SELECT 1"))
    updates = state.updates
    ready = updates is not None and updates.ready
    answer: dict[str, object] = {
        "status": "ok" if ready else "starting",
        "update_processes_warm": updates.warm_processes if updates is not None else 0,
        "update_processes": state.settings.update_workers if updates is None else updates.workers,
        "update_scheduler": state.settings.update_scheduler or None,
        "update_backlog": updates.backlog if updates is not None else None,
        "updates_done": updates.completed if updates is not None else None,
        "updates_failed": updates.failed if updates is not None else None,
    }
    if not ready:
        answer["detail"] = (
            "starting: the learner-update processes are loading the learners' compiled kernels"
        )
    return JSONResponse(answer, status_code=200 if ready else 503)
