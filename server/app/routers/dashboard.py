"""The experimenter's dashboard: an HTML page behind the admin token.

Signing in with ``BAM_ADMIN_TOKEN`` sets an HttpOnly, SameSite=Strict cookie holding an HMAC of
the token (never the token itself); the dashboard's JSON under ``/dashboard/api`` accepts that
cookie or ``Authorization: Bearer``, and answers with the same views as ``/api/admin``.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
from typing import Annotated, Any
from urllib.parse import quote

from fastapi import APIRouter, Depends, Form, Query, Request, Response
from fastapi.responses import HTMLResponse, RedirectResponse
from sqlalchemy import select

from server.app.deps import StateDep
from server.app.errors import ApiError
from server.app.models import LearningSession
from server.app.replica_models import ReplicaAssignment, ReplicaSubmission
from server.app.routers import admin
from server.app.routers.pages import templates
from server.app.schemas import (
    AdminEvaluation,
    AdminParticipant,
    AdminParticipantDetail,
    ExclusionRequest,
)
from server.app.state import ServerState

ADMIN_COOKIE = "bam_admin"
COOKIE_MAX_AGE = 12 * 3600


def _expected_token(state: ServerState) -> str | None:
    token = state.settings.admin_token
    if token is None or not token.get_secret_value():
        return None
    return token.get_secret_value()


def cookie_value(token: str) -> str:
    """What the admin cookie holds: an HMAC of the token, so the token never leaves the form."""
    return hmac.new(token.encode(), b"bam-study dashboard", hashlib.sha256).hexdigest()


def is_admin(request: Request, state: ServerState) -> bool:
    """The request carries the admin token (bearer header) or the dashboard's cookie."""
    expected = _expected_token(state)
    if expected is None:
        return False
    scheme, _, given = (request.headers.get("authorization") or "").partition(" ")
    if scheme.lower() == "bearer" and secrets.compare_digest(given.encode(), expected.encode()):
        return True
    cookie = request.cookies.get(ADMIN_COOKIE) or ""
    return secrets.compare_digest(cookie.encode(), cookie_value(expected).encode())


def require_dashboard_admin(request: Request, state: StateDep) -> None:
    if _expected_token(state) is None:
        raise ApiError(503, "the dashboard is disabled: set BAM_ADMIN_TOKEN")
    if not is_admin(request, state):
        raise ApiError(
            401, "sign in to the dashboard first", headers={"WWW-Authenticate": "Bearer"}
        )


DashboardAdmin = Depends(require_dashboard_admin)


def safe_next(target: str | None) -> str:
    """Only paths on this server (no scheme, no host) are followed after signing in."""
    if target and target.startswith("/") and not target.startswith("//") and "\\" not in target:
        return target
    return "/dashboard"


def login_page(request: Request, state: ServerState, next_path: str, error: str | None) -> Response:
    disabled = _expected_token(state) is None
    return templates.TemplateResponse(
        request,
        "dashboard_login.html",
        {"next": safe_next(next_path), "error": error, "disabled": disabled},
        status_code=401 if error else (503 if disabled else 200),
        headers={"Cache-Control": "no-store"},
    )


def login_redirect(path: str) -> RedirectResponse:
    return RedirectResponse(f"/dashboard/login?next={quote(path)}", status_code=303)


pages = APIRouter(tags=["dashboard"], include_in_schema=False)
api = APIRouter(prefix="/dashboard/api", tags=["dashboard"], dependencies=[DashboardAdmin])


@pages.get("/dashboard", response_class=HTMLResponse)
def dashboard_page(request: Request, state: StateDep) -> Response:
    if not is_admin(request, state):
        return login_redirect("/dashboard")
    return templates.TemplateResponse(
        request,
        "dashboard.html",
        {"study": state.study.public()},
        headers={"Cache-Control": "no-store"},
    )


@pages.get("/dashboard/login", response_class=HTMLResponse)
def dashboard_login_form(
    request: Request, state: StateDep, next: Annotated[str, Query()] = "/dashboard"
) -> Response:
    if is_admin(request, state):
        return RedirectResponse(safe_next(next), status_code=303)
    return login_page(request, state, next, None)


@pages.post("/dashboard/login", response_class=HTMLResponse)
def dashboard_login(
    request: Request,
    state: StateDep,
    token: Annotated[str, Form(max_length=512)],
    next: Annotated[str, Form(max_length=512)] = "/dashboard",
) -> Response:
    expected = _expected_token(state)
    if expected is None:
        return login_page(request, state, next, None)
    if not secrets.compare_digest(token.strip().encode(), expected.encode()):
        return login_page(request, state, next, "That is not the admin token.")
    response = RedirectResponse(safe_next(next), status_code=303)
    response.set_cookie(
        ADMIN_COOKIE,
        cookie_value(expected),
        max_age=COOKIE_MAX_AGE,
        httponly=True,
        samesite="strict",
        secure=state.settings.cookie_secure,
    )
    return response


@pages.post("/dashboard/logout")
def dashboard_logout() -> Response:
    response = RedirectResponse("/dashboard/login", status_code=303)
    response.delete_cookie(ADMIN_COOKIE)
    return response


@pages.get("/dashboard/export.zip", response_class=Response, dependencies=[DashboardAdmin])
def dashboard_export(state: StateDep, pseudonymize: Annotated[bool, Query()] = True) -> Response:
    """The export (CSV files and their data dictionary) as a zip, as ``/api/admin/export.zip``."""
    return admin.download_export(state, pseudonymize)


@api.get("/participants", response_model=list[AdminParticipant])
def participants(state: StateDep) -> list[AdminParticipant]:
    return admin.list_participants(state)


@api.get("/participants/{participant_id}")
def participant(participant_id: int, state: StateDep) -> dict[str, Any]:
    """``/api/admin/participants/{id}`` with each session's colour, to draw it."""
    answer = admin.read_participant(participant_id, state).model_dump(mode="json")
    with state.db.read() as s:
        rows = s.execute(
            select(LearningSession.id, LearningSession.colour_hex).where(
                LearningSession.participant_id == participant_id
            )
        )
        colours = {session_id: colour for session_id, colour in rows}
    for session in answer["sessions"]:
        session["colour_hex"] = colours.get(session["session_id"])
    return answer


@api.post("/participants/{participant_id}/exclusion", response_model=AdminParticipantDetail)
def exclude(participant_id: int, body: ExclusionRequest, state: StateDep) -> AdminParticipantDetail:
    """Exclude the participant from analysis, with the reason (as ``/api/admin``)."""
    return admin.exclude(participant_id, body, state)


@api.post("/participants/{participant_id}/inclusion", response_model=AdminParticipantDetail)
def include(participant_id: int, body: ExclusionRequest, state: StateDep) -> AdminParticipantDetail:
    """Include an excluded participant again, with the reason."""
    return admin.include(participant_id, state, body.reason)


@api.get("/sessions/{session_id}/evaluations", response_model=list[AdminEvaluation])
def evaluations(session_id: int, state: StateDep) -> list[AdminEvaluation]:
    return admin.list_evaluations(session_id, state)


@api.get("/sessions/{session_id}/replay")
def replay(session_id: int, state: StateDep) -> dict[str, Any]:
    """``/api/admin/sessions/{id}/replay`` with the agent's colour, to draw it as it was."""
    answer = admin.replay(session_id, state)
    with state.db.read() as s:
        session = s.get(LearningSession, session_id)
        answer["colour_hex"] = session.colour_hex if session is not None else None
    return answer


@api.get("/mturk")
def mturk_records(state: StateDep) -> dict[str, Any]:
    """The replica's assignments and every submission it recorded."""
    with state.db.read() as s:
        assignments = s.scalars(select(ReplicaAssignment).order_by(ReplicaAssignment.id)).all()
        submissions = s.scalars(select(ReplicaSubmission).order_by(ReplicaSubmission.id)).all()
    return {
        "assignments": [
            {
                "row": a.id,
                "hit_id": a.hit_id,
                "assignment_id": a.assignment_id,
                "worker_id": a.worker_id,
                "status": a.status,
                "accepted_at": a.accepted_at.isoformat(),
                "returned_at": a.returned_at.isoformat() if a.returned_at else None,
                "submitted_at": a.submitted_at.isoformat() if a.submitted_at else None,
            }
            for a in assignments
        ],
        "submissions": [
            {
                "assignment_id": x.assignment_id,
                "worker_id": x.worker_id,
                "hit_id": x.hit_id,
                "fields": x.fields,
                "submitted_at": x.submitted_at.isoformat(),
            }
            for x in submissions
        ],
    }
