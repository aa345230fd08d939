"""The local Prolific replica, served by the study server to rehearse a Prolific study offline.

- ``/prolific/api/v1/...``: the subset of Prolific's API the study server's client uses
  (``platforms/prolific_replica/``), with ``Authorization: Token $BAM_ADMIN_TOKEN``.
- ``/prolific``: the researcher's view (each study, its places, each submission with Prolific's
  statuses and times, the bonuses paid), behind the admin sign-in, and the participant's way
  in: take part with a generated PROLIFIC_PID (the study's external URL, its placeholders
  filled), return the submission (while active, or, as Prolific's "Return and cancel reward",
  once it awaits review: what a participant asked to return does), or let it time out at the
  study's maximum time.
- ``/prolific/submissions/complete?cc=CODE``: where the study's completion redirect lands; the
  code is checked against the study's completion codes.

One router for everything under ``/prolific`` (routers never import one another), so the
pages, the API and the completion redirect of the replica are one module.
"""

from __future__ import annotations

import asyncio
import functools
import json
import logging
import secrets
import time
from datetime import timedelta
from typing import Annotated, Any

import httpx
from fastapi import APIRouter, BackgroundTasks, Query, Request, Response
from fastapi.responses import HTMLResponse, JSONResponse, RedirectResponse
from sqlalchemy import select

from server.app.admin_auth import admin_token, client_address
from server.app.deps import StateDep, is_admin
from server.app.errors import ApiError
from server.app.participants import places
from server.app.platforms.prolific_capacity import Load, follow, followed_studies, steady
from server.app.platforms.prolific_replica import (
    PLACEHOLDERS,
    REPLICA_PATH,
    Delivery,
    StudyChange,
    barred,
    code_actions,
    concurrency_limit,
    delivered,
    deliveries,
    error_body,
    handle,
    hook_secret,
    new_id,
    places_taken,
    publish_due,
    requests_return,
    return_reason,
    signed,
    study_payload,
    submission_payload,
    submission_view,
    taking_part,
    workspace_of,
)
from server.app.platforms.prolific_sync import (
    STUDY_STATUS_EVENT,
    SUBMISSION_EVENT,
    WebhookRefused,
    apply_webhook,
    event_time,
    verify_any,
    webhook_secrets,
)
from server.app.platforms.review import ReviewRefused, ReviewUnavailable
from server.app.routers.common import login_redirect, notice, own_origin, templates
from server.app.state import ServerState
from server.app.storage.db import Database
from server.app.storage.models import utcnow
from server.app.storage.periodic import once_per_period
from server.app.storage.replica_models import (
    ProlificReplicaBonusSetup,
    ProlificReplicaPayment,
    ProlificReplicaStudy,
    ProlificReplicaSubmission,
)
from server.app.updates.queue import QueueState

router = APIRouter(prefix=REPLICA_PATH, tags=["prolific replica"], include_in_schema=False)

PID_COOKIE = "prolific_replica_pid"
log = logging.getLogger(__name__)


def send_event(db: Database, delivery: Delivery, event_time: str) -> None:
    """POST one signed webhook, as Prolific does, with the workspace's secret, and record how
    the target answered (a failure is logged; the poll catches up)."""
    with db.write() as s:
        secret = hook_secret(s, make=True)
    assert secret is not None
    body = json.dumps(delivery.payload).encode()
    headers = signed(secret, body, int(time.time()), event_time)
    try:
        httpx.post(
            delivery.target_url, content=body, headers=headers, timeout=10
        ).raise_for_status()
    except httpx.HTTPError as error:
        log.warning("the Prolific replica's webhook to %s failed: %s", delivery.target_url, error)
        delivered(db, delivery.event_id, False)
    else:
        delivered(db, delivery.event_id, True)


def _send(
    background: BackgroundTasks,
    request: Request,
    state: ServerState,
    events: list[tuple[str, str, dict[str, Any], str]],
) -> None:
    """Send each event ``(type, resource id, body, X-Timestamp)`` after answering, in order: to
    the replica's subscriptions to its type, or, with none, to this server's own webhook (no
    setting needed: the replica signs with its own workspace secret, which the webhook knows)."""
    own = f"{own_origin(request)}{REPLICA_PATH}/webhook"
    with state.db.write() as s:
        hook_secret(s, make=True)
        planned = [
            (delivery, at)
            for event_type, resource, payload, at in events
            for delivery in deliveries(s, event_type, resource, payload, own)
        ]
    for delivery, at in planned:
        background.add_task(send_event, state.db, delivery, at)


def notify(
    background: BackgroundTasks, request: Request, state: ServerState, submission: Any
) -> None:
    """The submission's new status, sent as ``submission.status.change`` after answering."""
    if submission is not None:
        payload = submission_payload(submission)
        stamp = str(int(time.time()))
        _send(background, request, state, [(SUBMISSION_EVENT, submission["id"], payload, stamp)])


def notify_study(
    background: BackgroundTasks, request: Request, state: ServerState, changes: list[StudyChange]
) -> None:
    """Each study's new status, sent as ``study.status.change`` after answering, in order (its
    ``X-Timestamp`` the change's own time, to the microsecond)."""
    if changes:
        events = [
            (STUDY_STATUS_EVENT, c.study_id, study_payload(c), c.at.isoformat()) for c in changes
        ]
        _send(background, request, state, events)


@router.api_route("/api/v1/{path:path}", methods=["GET", "POST", "PATCH", "DELETE"])
async def api(
    path: str, request: Request, state: StateDep, background: BackgroundTasks
) -> Response:
    expected = admin_token(state.settings)
    given = request.headers.get("Authorization", "")
    address = client_address(request)
    try:
        # The admin token, guessed here as at the dashboard's sign-in: past the failures
        # allowed, the address gets 429 whatever it sends.
        state.sign_ins.check(address)
    except ApiError as limited:
        return JSONResponse(
            error_body(429, limited.message), status_code=429, headers=limited.headers
        )
    if expected is None or not secrets.compare_digest(given.encode(), f"Token {expected}".encode()):
        state.sign_ins.failed(address)
        return JSONResponse(error_body(401, "Invalid token."), status_code=401)
    raw = await request.body()
    query = dict(request.query_params)
    workspace = workspace_of(state.settings)
    changes: list[StudyChange] = []
    headers: dict[str, str] = {}
    status, body = await state.run_db(
        lambda: handle(state.db, request.method, path, query, raw, workspace, changes, headers)
    )
    notify_study(background, request, state, changes)
    if body is None:
        return Response(status_code=status, headers=headers)
    return JSONResponse(body, status_code=status, headers=headers)


def time_out_overdue(state: ServerState) -> None:
    """Submissions still ACTIVE past their study's maximum time become TIMED-OUT."""
    now = utcnow()
    with state.db.write() as s:
        rows = s.execute(
            select(ProlificReplicaSubmission, ProlificReplicaStudy.maximum_allowed_time)
            .join(
                ProlificReplicaStudy, ProlificReplicaStudy.id == ProlificReplicaSubmission.study_id
            )
            .where(ProlificReplicaSubmission.status == "ACTIVE")
        ).all()
        for row, minutes in rows:
            if row.started_at + timedelta(minutes=minutes) < now:
                row.status = "TIMED-OUT"


def study_url(study: ProlificReplicaStudy, submission: ProlificReplicaSubmission) -> str:
    values = (submission.participant_id, study.id, submission.id)
    url = study.external_study_url
    for placeholder, value in zip(PLACEHOLDERS, values, strict=True):
        url = url.replace(placeholder, value)
    return url


@router.get("", response_class=HTMLResponse)
def researcher_view(request: Request, state: StateDep) -> Response:
    if not is_admin(request, state):
        return login_redirect("/prolific")
    time_out_overdue(state)
    with state.db.read() as s:
        studies = s.scalars(
            select(ProlificReplicaStudy).order_by(ProlificReplicaStudy.created_at.desc())
        ).all()
        listed: list[dict[str, Any]] = []
        for study in studies:
            listed.append(
                {
                    "study": study,
                    "taken": places_taken(s, study.id),
                    "submissions": s.scalars(
                        select(ProlificReplicaSubmission)
                        .where(ProlificReplicaSubmission.study_id == study.id)
                        .order_by(ProlificReplicaSubmission.started_at.desc())
                    ).all(),
                    "payments": s.execute(
                        select(ProlificReplicaPayment)
                        .join(
                            ProlificReplicaBonusSetup,
                            ProlificReplicaBonusSetup.id == ProlificReplicaPayment.setup_id,
                        )
                        .where(ProlificReplicaBonusSetup.study_id == study.id)
                        .order_by(ProlificReplicaPayment.id)
                    )
                    .scalars()
                    .all(),
                }
            )
    return templates.TemplateResponse(
        request,
        "prolific_replica.html",
        {"studies": listed, "title": state.study.title, "study": state.study.public()},
        headers={"Cache-Control": "no-store"},
    )


@router.post("/studies/{study_id}/take-part")
def take_part(
    study_id: str,
    request: Request,
    state: StateDep,
    background: BackgroundTasks,
    participant_id: Annotated[str | None, Query(pattern=r"^[0-9a-f]{24}$")] = None,
) -> Response:
    """A participant (a new generated PROLIFIC_PID, or ``participant_id``: one who took part
    before) takes a place and is sent to the study, unless the study's filters keep them out
    (its blocklists, its allowlist); the last place taken makes the study AWAITING REVIEW (its
    webhook sent)."""
    if not is_admin(request, state):
        return login_redirect("/prolific")
    time_out_overdue(state)
    with state.db.write() as s:
        due = publish_due(s)
    notify_study(background, request, state, due)
    with state.db.write() as s:
        # The study's row locked (PostgreSQL) until the place is taken: two participants at
        # once cannot both take the last place or the last concurrent one.
        study = s.get(ProlificReplicaStudy, study_id, with_for_update=True)
        if study is None:
            return notice(request, "No such study", f"The replica has no study {study_id}.", 404)
        why = barred(s, study, participant_id) if participant_id else None
        if why is not None:
            return notice(
                request,
                "Not eligible",
                f"Participant {participant_id} cannot take part in study {study_id}: {why}.",
                403,
            )
        if study.status != "ACTIVE":
            return notice(
                request, "Not open", f"Study {study_id} is {study.status}: it takes no one.", 409
            )
        if places_taken(s, study.id) >= study.total_available_places:
            # A full study sent START without more places: AWAITING REVIEW again.
            study.status = "AWAITING REVIEW"
            full = StudyChange(study.id, "AWAITING REVIEW", utcnow())
            notify_study(background, request, state, [full])
            return notice(request, "Full", "Every place of this study is taken.", 409)
        limit = concurrency_limit(study)
        if limit is not None and taking_part(s, study.id) >= limit:
            # As Prolific: no one new while max_concurrent_submissions are under way.
            return notice(
                request,
                "Busy",
                f"Study {study_id} has {limit} participant(s) taking part at once, its "
                "max_concurrent_submissions: a place opens when one finishes.",
                409,
            )
        submission = ProlificReplicaSubmission(
            id=new_id(),
            study_id=study.id,
            participant_id=participant_id or new_id(),
            status="ACTIVE",
            started_at=utcnow(),
        )
        s.add(submission)
        s.flush()
        filled = None
        if places_taken(s, study.id) >= study.total_available_places:
            study.status = "AWAITING REVIEW"  # as Prolific: no free place left
            filled = StudyChange(study.id, study.status, utcnow())
        url = study_url(study, submission)
        pid = submission.participant_id
    if filled is not None:
        notify_study(background, request, state, [filled])
    response = RedirectResponse(url, status_code=303)
    response.set_cookie(PID_COOKIE, pid, httponly=True, samesite="lax")
    return response


def _end(
    request: Request,
    state: ServerState,
    background: BackgroundTasks,
    submission_id: str,
    status: str,
    sources: tuple[str, ...],
) -> Response:
    if not is_admin(request, state):
        return login_redirect("/prolific")
    with state.db.write() as s:
        row = s.get(ProlificReplicaSubmission, submission_id)
        if row is None or row.status not in sources:
            now = "not found" if row is None else row.status
            return notice(
                request,
                "Cannot",
                f"This submission is {now}: only one that is {' or '.join(sources)} can become "
                f"{status}.",
                409,
            )
        # The place is free again: an ACTIVE study offers it at once; a full one (AWAITING
        # REVIEW) stays so until the researcher sends START, as on Prolific.
        row.status = status
        view = submission_view(row)
    notify(background, request, state, view)
    return RedirectResponse("/prolific", status_code=303)


@router.post("/submissions/{submission_id}/return")
def return_submission(
    submission_id: str, request: Request, state: StateDep, background: BackgroundTasks
) -> Response:
    # As Prolific: an active submission, or a completed one awaiting review ("Return and cancel
    # reward"), which is what a participant asked to return (REQUEST_RETURN) does.
    return _end(
        request, state, background, submission_id, "RETURNED", ("ACTIVE", "AWAITING REVIEW")
    )


@router.post("/submissions/{submission_id}/time-out")
def time_out(
    submission_id: str, request: Request, state: StateDep, background: BackgroundTasks
) -> Response:
    return _end(request, state, background, submission_id, "TIMED-OUT", ("ACTIVE",))


@router.get("/submissions/complete", response_class=HTMLResponse)
def complete(
    request: Request, state: StateDep, background: BackgroundTasks, cc: str = ""
) -> Response:
    """The completion redirect's landing: the participant's active submission is completed
    with the code, when the code is one of the study's (else Prolific's 'invalid code')."""
    pid = request.cookies.get(PID_COOKIE, "")
    view = None
    with state.db.write() as s:
        row = s.scalar(
            select(ProlificReplicaSubmission)
            .where(ProlificReplicaSubmission.participant_id == pid)
            .order_by(ProlificReplicaSubmission.started_at.desc())
            .limit(1)
        )
        if row is None:
            return notice(request, "No submission", "You have not taken part in a study.", 404)
        study = s.get(ProlificReplicaStudy, row.study_id)
        codes = {
            c.get("code"): c for c in (study.fields.get("completion_codes", []) if study else [])
        }
        if cc not in codes:
            return notice(
                request,
                "Invalid completion code",
                f"{cc!r} is not a completion code of this study.",
                400,
            )
        if row.status not in ("ACTIVE", "AWAITING REVIEW"):
            return notice(request, "Already ended", f"This submission is {row.status}.", 409)
        row.study_code = cc
        row.completed_at = utcnow()
        row.status = "AWAITING REVIEW"
        code_actions(s, codes[cc], row.participant_id)  # its participant groups
        asked = requests_return(codes[cc])
        if asked and row.return_requested is None:
            # As Prolific: the submission is completed and the participant asked to return
            # it; it is RETURNED only if they do (and approved after 21 days if they never do).
            row.return_requested = row.completed_at
        status, submission_id = row.status, row.id
        view = submission_view(row)
    notify(background, request, state, view)
    if asked:
        # As Prolific's page for such a code: the researcher's reason, and the way to return.
        return notice(
            request,
            "Return requested",
            f"Completion code {cc} accepted: the submission is {status}, and the researcher "
            f"asks you to return it: \u201c{return_reason(codes[cc])}\u201d Returning it "
            "cancels its reward; a submission never returned is approved, and paid, "
            "automatically after 21 days.",
            200,
            form=(f"{REPLICA_PATH}/submissions/{submission_id}/return", "return", "Return"),
        )
    return notice(
        request,
        "Submission recorded",
        f"Completion code {cc} accepted: the submission is {status}.",
        200,
    )


@router.post("/webhook")
async def webhook(request: Request, state: StateDep) -> Response:
    """Prolific's webhook (signed with the workspace's secret that ``bam-study prolific hooks``
    stored, or ``BAM_PROLIFIC_WEBHOOK_SECRET``, or this server's replica's own) for ``submission.status.change``,
    ``study.status.change`` and ``study.has_high_return_rate`` (``prolific_sync``): a
    forged, unsigned or old request is refused (401) and changes nothing; a redelivered event
    is answered 200 and applied once."""
    known = await state.run_db(lambda: webhook_secrets(state.db, state.settings))
    if not known:
        return JSONResponse(
            {
                "detail": "no webhook secret: run `bam-study prolific hooks` (it makes the "
                "workspace's secret and stores it here), or set BAM_PROLIFIC_WEBHOOK_SECRET"
            },
            status_code=503,
        )
    body = await request.body()
    try:
        verify_any(
            known,
            request.headers.get("X-Prolific-Request-Timestamp"),
            request.headers.get("X-Prolific-Request-Signature"),
            body,
        )
    except WebhookRefused as refused:
        return JSONResponse({"detail": f"webhook refused: {refused}"}, status_code=401)
    event_id = request.headers.get("X-Event-ID", "")
    if not event_id or len(event_id) > 128:
        return JSONResponse({"detail": "the request has no X-Event-ID"}, status_code=400)
    try:
        payload = json.loads(body)
    except ValueError:
        return JSONResponse({"detail": "the body is not JSON"}, status_code=400)
    if not isinstance(payload, dict):
        return JSONResponse({"detail": "the body is not a JSON object"}, status_code=400)
    try:
        happened_at = event_time(request.headers.get("X-Timestamp"))
        result = await state.run_db(lambda: apply_webhook(state.db, event_id, payload, happened_at))
    except ValueError as error:
        return JSONResponse({"detail": str(error)}, status_code=400)
    return JSONResponse({"result": result})


# -- the study's capacity held on Prolific ------------------------------------------------------
FOLLOW_SECONDS = 15.0  # how often the server compares its load with its Prolific studies


def server_load(state: ServerState, queue: QueueState | None) -> Load:
    """The readings ``prolific_capacity`` follows: the participants the server admits at once,
    its update queue (``queue``: the update manager's, read on its event loop) and its line."""
    with state.db.connect() as c:
        waiting = places.waiting_count(c, utcnow())
    return Load(
        limit=places.study_limit(state),
        awaited=queue.sessions_awaited if queue is not None else 0,
        oldest_wait_seconds=queue.oldest_wait_seconds if queue is not None else 0.0,
        waiting=waiting,
    )


def follow_capacity(
    state: ServerState, queue: QueueState | None, previous: Load | None = None
) -> Load:
    """One comparison of the server's load with each Prolific study it follows (a study
    Prolific cannot be asked about is left for the next one); ``previous``: the reading before,
    which a wait for updates must have shown too (``steady``; None: this reading alone). The
    reading, for the next."""
    reading = server_load(state, queue)
    load = reading if previous is None else steady(previous, reading)
    studies = followed_studies(state.db)
    if not studies:
        return reading
    client = getattr(state.review_backend("prolific"), "client", None)
    if client is None:
        return reading
    for study_id in studies:
        try:
            follow(state.db, client, study_id, load)
        except (ReviewRefused, ReviewUnavailable) as error:
            log.warning("could not hold Prolific study %s to the capacity: %s", study_id, error)
    return reading


async def follow_capacity_forever(state: ServerState, server: str) -> None:
    """``follow_capacity`` every ``FOLLOW_SECONDS`` while the server runs, each reading
    judged with the one before (a wait must last two readings to pause a study); on the
    whole deployment once a period, by whichever server comes first (``once_per_period``), so
    that several servers do not each set the study's concurrency."""
    previous: Load | None = Load(None, 0, 0.0, 0)  # before the first: no wait

    def follow_once(queue: QueueState | None) -> None:
        nonlocal previous
        previous = follow_capacity(state, queue, previous)

    while True:
        await asyncio.sleep(FOLLOW_SECONDS)
        queue = state.updates.queue() if state.updates is not None else None
        try:
            await asyncio.to_thread(
                once_per_period,
                state.db,
                "prolific capacity",
                FOLLOW_SECONDS,
                server,
                functools.partial(follow_once, queue),
            )
        except Exception:
            log.exception("could not hold the Prolific studies to the capacity")
