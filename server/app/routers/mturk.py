"""A local Mechanical Turk replica, behind the admin token, to try the whole HIT before paying.

It plays the platform's side as an ExternalQuestion HIT does: the HIT page lists the study; a
worker (any id the experimenter types) previews it (the study in an iframe with
``assignmentId=ASSIGNMENT_ID_NOT_AVAILABLE``), accepts it (an assignment id), works on it (the
study in an iframe with exactly ``assignmentId``, ``hitId``, ``workerId`` and ``turkSubmitTo``,
which points back at this server), and either submits (the page POSTs its form from the top
window to ``{turkSubmitTo}/mturk/externalSubmit``, recorded here with every field) or returns
the HIT, after which the same assignment id goes to the next worker who accepts, as on MTurk.
Unlike MTurk, the replica tells the study of a return at once (the participant is marked
returned).
The requester's approvals, rejections and bonuses (``platforms.mturk.MTurkReplicaBackend``, from the
dashboard) show on the HIT page.
"""

from __future__ import annotations

import re
import secrets
from typing import Annotated
from urllib.parse import urlencode

from fastapi import APIRouter, Form, Request, Response
from fastapi.responses import HTMLResponse, RedirectResponse
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from server.app.deps import RowId, StateDep, is_admin
from server.app.participants.arrival import return_assignment
from server.app.platforms.mturk import PREVIEW_ASSIGNMENT
from server.app.routers.common import login_redirect, notice, own_origin, templates
from server.app.schemas import ID_PATTERN
from server.app.state import ServerState
from server.app.storage.db import advisory_lock_key
from server.app.storage.models import utcnow
from server.app.storage.replica_models import (
    ReplicaAssignment,
    ReplicaBonus,
    ReplicaHit,
    ReplicaSubmission,
)
from server.app.storage.vocabulary import ReplicaAssignmentStatus

router = APIRouter(prefix="/mturk", tags=["mturk replica"], include_in_schema=False)

ID_ALPHABET = "ABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789"
_HIT_LOCK = select(func.pg_advisory_xact_lock(advisory_lock_key("bam-study mturk replica hit")))
MAX_FIELDS = 50


def new_id(length: int = 30) -> str:
    """An id shaped like MTurk's (30 upper-case letters and digits)."""
    return "".join(secrets.choice(ID_ALPHABET) for _ in range(length))


def the_hit(s: Session, state: ServerState) -> ReplicaHit:
    """The replica's one HIT, made the first time. In a write transaction, which holds the HIT
    until it ends (PostgreSQL: an advisory lock; SQLite's write transaction excludes every
    other writer already): workers accepting at once, on one server or several, make one HIT
    and get one assignment each, and two never get the same returned assignment."""
    if s.get_bind().dialect.name == "postgresql":
        s.execute(_HIT_LOCK)
    hit = s.scalar(select(ReplicaHit).order_by(ReplicaHit.id).limit(1))
    if hit is None:
        hit = ReplicaHit(hit_id=new_id(), title=state.study.title, created_at=utcnow())
        s.add(hit)
        s.flush()
    return hit


def reusable_assignment_id(s: Session, hit_id: str) -> str | None:
    """The oldest assignment id that was returned and has not gone to another worker since."""
    rows = s.execute(
        select(ReplicaAssignment.assignment_id, ReplicaAssignment.status)
        .where(ReplicaAssignment.hit_id == hit_id)
        .order_by(ReplicaAssignment.id)
    ).all()
    taken = {row.assignment_id for row in rows if row.status != ReplicaAssignmentStatus.RETURNED}
    for row in rows:
        if row.status == ReplicaAssignmentStatus.RETURNED and row.assignment_id not in taken:
            return str(row.assignment_id)
    return None


def valid_worker_id(value: str) -> bool:
    return re.fullmatch(ID_PATTERN, value) is not None


def hit_page(
    request: Request, state: ServerState, error: str | None = None, worker: str = ""
) -> Response:
    with state.db.write() as s:
        hit = the_hit(s, state)
        assignments = s.scalars(
            select(ReplicaAssignment)
            .where(ReplicaAssignment.hit_id == hit.hit_id)
            .order_by(ReplicaAssignment.id.desc())
        ).all()
        submissions = s.scalars(
            select(ReplicaSubmission).order_by(ReplicaSubmission.id.desc())
        ).all()
        bonuses = s.scalars(select(ReplicaBonus).order_by(ReplicaBonus.id.desc())).all()
    return templates.TemplateResponse(
        request,
        "mturk_hit.html",
        {
            "study": state.study.public(),
            "hit": hit,
            "assignments": assignments,
            "submissions": submissions,
            "bonuses": bonuses,
            "error": error,
            "worker": worker or f"WORKER{secrets.randbelow(10**6):06d}",
        },
        status_code=400 if error else 200,
        headers={"Cache-Control": "no-store"},
    )


@router.get("", response_class=HTMLResponse)
def hits(request: Request, state: StateDep) -> Response:
    if not is_admin(request, state):
        return login_redirect("/mturk")
    return hit_page(request, state)


@router.get("/preview", response_class=HTMLResponse)
def preview(request: Request, state: StateDep, workerId: str = "") -> Response:
    if not is_admin(request, state):
        return login_redirect("/mturk")
    with state.db.write() as s:
        hit = the_hit(s, state)
    # MTurk previews append the preview assignment id and the HIT id only.
    query = urlencode({"assignmentId": PREVIEW_ASSIGNMENT, "hitId": hit.hit_id})
    return templates.TemplateResponse(
        request,
        "mturk_frame.html",
        {
            "study": state.study.public(),
            "hit": hit,
            "worker": workerId if valid_worker_id(workerId) else "",
            "assignment": None,
            "frame_url": f"/study?{query}",
        },
        headers={"Cache-Control": "no-store"},
    )


@router.post("/accept")
def accept(
    request: Request, state: StateDep, workerId: Annotated[str, Form(max_length=128)]
) -> Response:
    if not is_admin(request, state):
        return login_redirect("/mturk")
    worker = workerId.strip()
    if not valid_worker_id(worker):
        return hit_page(
            request, state, "A worker id is 1 to 128 letters, digits, '-' or '_'.", worker
        )
    with state.db.write() as s:
        hit = the_hit(s, state)
        # As on MTurk: one assignment of a HIT per worker. The one they hold is theirs to go on
        # with; a worker who submitted cannot take the HIT again.
        row = s.scalars(
            select(ReplicaAssignment).where(
                ReplicaAssignment.hit_id == hit.hit_id,
                ReplicaAssignment.worker_id == worker,
                ReplicaAssignment.status != ReplicaAssignmentStatus.RETURNED,
            )
        ).first()
        if row is None:
            row = ReplicaAssignment(
                hit_id=hit.hit_id,
                assignment_id=reusable_assignment_id(s, hit.hit_id) or new_id(),
                worker_id=worker,
                status=ReplicaAssignmentStatus.ACCEPTED,
                accepted_at=utcnow(),
            )
            s.add(row)
            s.flush()
        row_id, status, assignment_id = row.id, row.status, row.assignment_id
    if status != ReplicaAssignmentStatus.ACCEPTED:
        return hit_page(
            request,
            state,
            f"Worker {worker} has already submitted assignment {assignment_id} of this HIT: a "
            "worker does a HIT once.",
            worker,
        )
    return RedirectResponse(f"/mturk/work/{row_id}", status_code=303)


@router.get("/work/{row_id}", response_class=HTMLResponse)
def work(row_id: RowId, request: Request, state: StateDep) -> Response:
    if not is_admin(request, state):
        return login_redirect(f"/mturk/work/{row_id}")
    with state.db.read() as s:
        row = s.get(ReplicaAssignment, row_id)
        hit = s.scalar(select(ReplicaHit).where(ReplicaHit.hit_id == row.hit_id)) if row else None
    if row is None or hit is None:
        return notice(request, "No such assignment", f"There is no assignment {row_id}.", 404)
    if row.status != ReplicaAssignmentStatus.ACCEPTED:
        return notice(
            request,
            f"This assignment was {row.status}",
            f"Worker {row.worker_id} {row.status} assignment {row.assignment_id}. "
            "Go back to the HIT page to accept it again.",
            409,
        )
    # Exactly the parameters MTurk appends to an ExternalQuestion's URL.
    query = urlencode(
        {
            "assignmentId": row.assignment_id,
            "hitId": row.hit_id,
            "workerId": row.worker_id,
            "turkSubmitTo": own_origin(request),
        }
    )
    return templates.TemplateResponse(
        request,
        "mturk_frame.html",
        {
            "study": state.study.public(),
            "hit": hit,
            "worker": row.worker_id,
            "assignment": row,
            "frame_url": f"/study?{query}",
        },
        headers={"Cache-Control": "no-store"},
    )


@router.post("/work/{row_id}/return")
def return_hit(row_id: RowId, request: Request, state: StateDep) -> Response:
    if not is_admin(request, state):
        return login_redirect("/mturk")
    with state.db.write() as s:
        row = s.get(ReplicaAssignment, row_id)
        if row is None or row.status != ReplicaAssignmentStatus.ACCEPTED:
            return notice(request, "Cannot return", "This assignment is not being worked on.", 409)
        row.status = ReplicaAssignmentStatus.RETURNED
        row.returned_at = utcnow()
        # The study hears of it at once, so that the replica and the study agree on who holds
        # the assignment when it goes to the next worker (or back to this one).
        return_assignment(s.connection(), row.worker_id, row.assignment_id)
    return RedirectResponse("/mturk", status_code=303)


@router.post("/externalSubmit", response_class=HTMLResponse)
async def external_submit(request: Request, state: StateDep) -> Response:
    """What MTurk does with the page's form: check the assignment, record every field."""
    if not is_admin(request, state):
        return notice(
            request,
            "Not signed in to the replica",
            "This Mechanical Turk replica only takes submissions from the experimenter's "
            "browser: sign in to the dashboard first.",
            401,
        )
    form = await request.form()
    fields: dict[str, str | list[str]] = {}
    for key in form:
        values = [str(v) for v in form.getlist(key)]
        fields[key] = values[0] if len(values) == 1 else values
    assignment_id = fields.get("assignmentId")
    if not isinstance(assignment_id, str) or not assignment_id:
        return notice(request, "Submission refused", "The form has no assignmentId.", 400)
    if len(fields) < 2 or len(fields) > MAX_FIELDS:
        return notice(
            request,
            "Submission refused",
            "MTurk needs the assignmentId and at least one other field.",
            400,
        )
    with state.db.write() as s:
        row = s.scalar(
            select(ReplicaAssignment)
            .where(ReplicaAssignment.assignment_id == assignment_id)
            .order_by(ReplicaAssignment.id.desc())
            .limit(1)
        )
        if row is None or row.status != ReplicaAssignmentStatus.ACCEPTED:
            what = "is not accepted by any worker" if row is None else f"was {row.status}"
            return notice(request, "Submission refused", f"Assignment {assignment_id} {what}.", 409)
        now = utcnow()
        row.status = ReplicaAssignmentStatus.SUBMITTED
        row.submitted_at = now
        s.add(
            ReplicaSubmission(
                assignment_row_id=row.id,
                hit_id=row.hit_id,
                assignment_id=row.assignment_id,
                worker_id=row.worker_id,
                fields=fields,
                submitted_at=now,
            )
        )
        worker = row.worker_id
    return templates.TemplateResponse(
        request,
        "mturk_submitted.html",
        {"assignment_id": assignment_id, "worker": worker, "fields": fields},
    )
