"""The experimenter's dashboard: an HTML page behind the admin token.

Signing in with ``BAM_ADMIN_TOKEN`` starts a dashboard session (``admin_auth``): an HttpOnly,
SameSite=Strict cookie with a random id, its expiry and a signature, which signing out revokes.
The dashboard's JSON under ``/dashboard/api`` accepts that cookie or ``Authorization: Bearer``,
and answers with the same views as ``/api/admin``. Failed sign-ins are limited per address.
"""

from __future__ import annotations

import secrets
from typing import Annotated, Any
from urllib.parse import quote

from fastapi import APIRouter, Depends, Form, Query, Request, Response
from fastapi.responses import HTMLResponse, RedirectResponse
from sqlalchemy import select

from server.app.admin_auth import SESSION_SECONDS, admin_token, bearer_is_admin, client_address
from server.app.deps import RowId, StateDep
from server.app.errors import ApiError
from server.app.models import LearningSession
from server.app.replica_models import ReplicaAssignment, ReplicaSubmission
from server.app.routers import admin
from server.app.routers.pages import templates
from server.app.schemas import (
    AdminEvaluation,
    AdminParticipant,
    AdminParticipantDetail,
    BonusRequest,
    ExclusionRequest,
    ReviewRequest,
)
from server.app.state import ServerState

ADMIN_COOKIE = "bam_admin"


def is_admin(request: Request, state: ServerState) -> bool:
    """The request carries the admin token (bearer header) or a dashboard session's cookie."""
    expected = admin_token(state.settings)
    if expected is None:
        return False
    if bearer_is_admin(request, expected, state.sign_ins):
        return True
    cookie = request.cookies.get(ADMIN_COOKIE)
    return cookie is not None and state.admin_sessions.valid(expected, cookie)


def require_dashboard_admin(request: Request, state: StateDep) -> None:
    if admin_token(state.settings) is None:
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


def login_page(
    request: Request,
    state: ServerState,
    next_path: str,
    error: str | None,
    status_code: int = 401,
    headers: dict[str, str] | None = None,
) -> Response:
    disabled = admin_token(state.settings) is None
    return templates.TemplateResponse(
        request,
        "dashboard_login.html",
        {"next": safe_next(next_path), "error": error, "disabled": disabled},
        status_code=status_code if error else (503 if disabled else 200),
        headers={"Cache-Control": "no-store", **(headers or {})},
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
    expected = admin_token(state.settings)
    if expected is None:
        return login_page(request, state, next, None)
    address = client_address(request)
    try:
        state.sign_ins.check(address)
    except ApiError as refused:
        return login_page(request, state, next, refused.message, 429, refused.headers)
    if not secrets.compare_digest(token.strip().encode(), expected.encode()):
        state.sign_ins.failed(address)
        return login_page(request, state, next, "That is not the admin token.")
    response = RedirectResponse(safe_next(next), status_code=303)
    response.set_cookie(
        ADMIN_COOKIE,
        state.admin_sessions.start(expected),
        max_age=SESSION_SECONDS,
        httponly=True,
        samesite="strict",
        secure=state.settings.cookie_secure,
    )
    return response


@pages.post("/dashboard/logout")
def dashboard_logout(request: Request, state: StateDep) -> Response:
    """Sign out: the session is revoked (a copy of its cookie stops working too)."""
    expected = admin_token(state.settings)
    cookie = request.cookies.get(ADMIN_COOKIE)
    if expected is not None and cookie is not None:
        state.admin_sessions.end(expected, cookie)
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
def participant(participant_id: RowId, state: StateDep) -> dict[str, Any]:
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
def exclude(
    participant_id: RowId, body: ExclusionRequest, state: StateDep
) -> AdminParticipantDetail:
    """Exclude the participant from analysis, with the reason (as ``/api/admin``)."""
    return admin.exclude(participant_id, body, state)


@api.post("/participants/{participant_id}/inclusion", response_model=AdminParticipantDetail)
def include(
    participant_id: RowId, body: ExclusionRequest, state: StateDep
) -> AdminParticipantDetail:
    """Include an excluded participant again, with the reason."""
    return admin.include(participant_id, state, body.reason)


@api.post("/participants/{participant_id}/erasure", response_model=admin.Erased)
def erase(participant_id: RowId, state: StateDep) -> admin.Erased:
    """Erase the participant on their request (as ``/api/admin``)."""
    return admin.erase(participant_id, state)


@api.post("/participants/{participant_id}/approval", response_model=AdminParticipantDetail)
def approve(participant_id: RowId, body: ReviewRequest, state: StateDep) -> AdminParticipantDetail:
    """Approve the participant's submitted MTurk assignment (as ``/api/admin``)."""
    return admin.approve(participant_id, body, state)


@api.post("/participants/{participant_id}/rejection", response_model=AdminParticipantDetail)
def reject(participant_id: RowId, body: ReviewRequest, state: StateDep) -> AdminParticipantDetail:
    """Reject the participant's submitted MTurk assignment, with feedback."""
    return admin.reject(participant_id, body, state)


@api.post("/participants/{participant_id}/bonuses", response_model=AdminParticipantDetail)
def send_bonus(
    participant_id: RowId, body: BonusRequest, state: StateDep
) -> AdminParticipantDetail:
    """Pay the participant's worker a bonus, once per ``unique_token``."""
    return admin.send_bonus(participant_id, body, state)


@api.get("/sessions/{session_id}/evaluations", response_model=list[AdminEvaluation])
def evaluations(session_id: RowId, state: StateDep) -> list[AdminEvaluation]:
    return admin.list_evaluations(session_id, state)


@api.get("/sessions/{session_id}/replay")
def replay(session_id: RowId, state: StateDep) -> dict[str, Any]:
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
