"""The experimenter's endpoints, behind ``Authorization: Bearer $BAM_ADMIN_TOKEN``.

One router (``/api/admin``, the admin token checked once for all): every endpoint of the
experimenter's dashboard, in the order the OpenAPI document lists them.
"""

from __future__ import annotations

from datetime import timedelta
from typing import Annotated, Any

from fastapi import APIRouter, Query, Response
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from server.app import platform_registry as registry
from server.app.deps import AdminDep, RowId, StateDep
from server.app.errors import ApiError
from server.app.export.files import export_zip
from server.app.export.tables import export_tables
from server.app.participants import assignment, places, teaching
from server.app.platforms import prolific_capacity, prolific_sync, review
from server.app.rights.erasure import Erased, erase_participant
from server.app.schemas import (
    AdminEvaluation,
    AdminEvent,
    AdminParticipant,
    AdminParticipantDetail,
    AdminReplay,
    AdminSession,
    BonusRequest,
    BonusView,
    BulkApprovalRequest,
    BulkApprovalView,
    ExclusionRequest,
    HighReturnRateView,
    ProlificStudyChangeView,
    ProlificStudyView,
    QueueView,
    ReplicaAssignmentView,
    ReplicaRecords,
    ReplicaSubmissionView,
    ReviewRequest,
    ReviewView,
    ServerRow,
    StatusChangeView,
)
from server.app.state import ServerState
from server.app.storage.figures import participant_figures
from server.app.storage.models import (
    Bonus,
    Event,
    LearnerUpdate,
    LearningSession,
    Participant,
    ProlificStudy,
    Review,
    StatusChange,
    utcnow,
)
from server.app.storage.replica_models import ReplicaAssignment, ReplicaSubmission
from server.app.storage.vocabulary import (
    IN_PROGRESS,
    ErasedBy,
    ExclusionMark,
    ParticipantStatus,
    ReviewDecision,
    SessionStatus,
    UpdateStatus,
)
from server.app.updates.servers import deployment_servers

STATUSES = tuple(ParticipantStatus)

router = APIRouter(prefix="/api/admin", tags=["admin"], dependencies=[AdminDep])


def _final_returns(s: Session, session_ids: list[int]) -> dict[int, float | None]:
    if not session_ids:
        return {}
    latest = (
        select(LearnerUpdate.session_id, func.max(LearnerUpdate.update_index).label("index"))
        .where(LearnerUpdate.session_id.in_(session_ids), LearnerUpdate.status == UpdateStatus.DONE)
        .group_by(LearnerUpdate.session_id)
        .subquery()
    )
    rows = s.execute(
        select(LearnerUpdate.session_id, LearnerUpdate.normalized_return).join(
            latest,
            (LearnerUpdate.session_id == latest.c.session_id)
            & (LearnerUpdate.update_index == latest.c.index),
        )
    )
    return {session_id: value for session_id, value in rows}


def _admin_sessions(s: Session, sessions: list[LearningSession]) -> list[AdminSession]:
    returns = _final_returns(s, [x.id for x in sessions])
    return [
        AdminSession(
            session_id=x.id,
            participant_id=x.participant_id,
            kind=x.kind,
            position=x.position,
            domain=x.domain,
            environment=x.environment,
            learner=x.learner,
            colour=x.colour_name,
            colour_hex=x.colour_hex,
            status=x.status,
            mode=x.mode,
            task=x.task,
            started_at=x.started_at,
            finished_at=x.finished_at,
            completed=x.completed,
            episodes=x.episodes,
            actions=x.actions,
            pending_updates=max(0, x.updates_requested - x.updates_processed),
            final_normalized_return=returns.get(x.id),
        )
        for x in sessions
    ]


# The dashboard warns this many days before the platform approves a submission by itself.
AUTO_APPROVAL_WARNING_DAYS = 7


def _admin_participant(
    p: Participant, sessions: list[LearningSession], completed_at: Any
) -> AdminParticipant:
    figures = participant_figures(p, [x for x in sessions if x.kind == "study"], completed_at)
    platform = registry.platform(p.platform)
    auto_approval = platform.auto_approval_at(p)
    warn_from = utcnow() + timedelta(days=AUTO_APPROVAL_WARNING_DAYS)
    return AdminParticipant(
        participant_id=p.id,
        platform=p.platform,
        platform_participant_id=p.platform_participant_id,
        platform_submission_id=p.platform_submission_id,
        platform_study_id=p.platform_study_id,
        status=p.status,
        prolific_status=p.platform_status,
        return_requested_at=p.platform_return_requested_at,
        awaits_decision=platform.awaits_decision(p),
        auto_approval_at=auto_approval,
        auto_approval_soon=auto_approval is not None and auto_approval <= warn_from,
        domain=p.domain,
        excluded=p.excluded_at is not None,
        exclusion_reason=p.exclusion_reason,
        created_at=p.created_at,
        last_seen_at=p.last_seen_at,
        minutes=figures.minutes,
        agents_finished=figures.agents_finished,
        agents=figures.agents,
        completion_code=p.completion_code,
    )


def _completed_at(s: Session, participant_ids: list[int]) -> dict[int, Any]:
    rows = s.execute(
        select(StatusChange.participant_id, func.min(StatusChange.at))
        .where(
            StatusChange.participant_id.in_(participant_ids),
            StatusChange.status == ParticipantStatus.COMPLETED,
        )
        .group_by(StatusChange.participant_id)
    )
    return {participant_id: at for participant_id, at in rows}


@router.get("/participants", response_model=list[AdminParticipant])
def list_participants(
    state: StateDep,
    status: Annotated[str | None, Query(description="Only this status.")] = None,
) -> list[AdminParticipant]:
    """Every participant with status, domain, progress and time spent."""
    if status is not None and status not in STATUSES:
        raise ApiError(400, f"unknown status {status!r}; valid: {', '.join(STATUSES)}")
    with state.db.read() as s:
        query = select(Participant).order_by(Participant.id)
        if status is not None:
            query = query.where(Participant.status == status)
        participants = s.scalars(query).all()
        ids = [p.id for p in participants]
        sessions = s.scalars(
            select(LearningSession).where(LearningSession.participant_id.in_(ids))
        ).all()
        completed = _completed_at(s, ids)
    by_participant: dict[int, list[LearningSession]] = {}
    for x in sessions:
        by_participant.setdefault(x.participant_id, []).append(x)
    return [
        _admin_participant(p, by_participant.get(p.id, []), completed.get(p.id))
        for p in participants
    ]


def _participant_detail(s: Session, participant_id: int) -> AdminParticipantDetail:
    p = s.get(Participant, participant_id)
    if p is None:
        raise ApiError(404, f"no participant {participant_id}")
    sessions = list(
        s.scalars(
            select(LearningSession)
            .where(LearningSession.participant_id == p.id)
            .order_by(LearningSession.ordinal)
        )
    )
    changes = s.scalars(
        select(StatusChange).where(StatusChange.participant_id == p.id).order_by(StatusChange.id)
    ).all()
    base = _admin_participant(p, sessions, _completed_at(s, [p.id]).get(p.id))
    decision = s.scalar(select(Review).where(Review.participant_id == p.id))
    bonuses = s.scalars(select(Bonus).where(Bonus.participant_id == p.id).order_by(Bonus.id))
    return AdminParticipantDetail(
        **base.model_dump(),
        status_changes=[StatusChangeView(status=c.status, at=c.at, note=c.note) for c in changes],
        sessions=_admin_sessions(s, sessions),
        review=None
        if decision is None
        else ReviewView(
            decision=decision.decision,  # type: ignore[arg-type]
            message=decision.message,
            rejection_category=decision.rejection_category,
            backend=decision.backend,
            state=decision.state,  # type: ignore[arg-type]
            decided_at=decision.decided_at,
        ),
        bonuses=[
            BonusView(
                amount=review.money(b.amount_cents),
                currency=b.currency,
                reason=b.reason,
                unique_token=b.unique_token,
                backend=b.backend,
                state=b.state,
                setup_id=b.setup_id,
                pay_sent_at=b.pay_sent_at,
                paid_at=b.paid_at,
                note=review.bonus_note(b),
            )
            for b in bonuses
        ],
    )


@router.get("/participants/{participant_id}", response_model=AdminParticipantDetail)
def read_participant(participant_id: RowId, state: StateDep) -> AdminParticipantDetail:
    """One participant: status history and learning sessions."""
    with state.db.read() as s:
        return _participant_detail(s, participant_id)


@router.post("/participants/{participant_id}/exclusion", response_model=AdminParticipantDetail)
def exclude(
    participant_id: RowId, body: ExclusionRequest, state: StateDep
) -> AdminParticipantDetail:
    """Exclude the participant from analysis (their flow goes on unchanged)."""
    with state.db.write() as s:
        p = s.get(Participant, participant_id)
        if p is None:
            raise ApiError(404, f"no participant {participant_id}")
        if p.excluded_at is not None:
            raise ApiError(409, f"participant {participant_id} is already excluded")
        now = utcnow()
        p.excluded_at = now
        p.exclusion_reason = body.reason
        s.add(
            StatusChange(
                participant_id=p.id, status=ExclusionMark.EXCLUDED, at=now, note=body.reason
            )
        )
    with state.db.read() as s:
        return _participant_detail(s, participant_id)


@router.post("/participants/{participant_id}/inclusion", response_model=AdminParticipantDetail)
def include(
    participant_id: RowId, body: ExclusionRequest, state: StateDep
) -> AdminParticipantDetail:
    """Undo an exclusion, with the reason (kept in the status history)."""
    reason = body.reason
    with state.db.write() as s:
        p = s.get(Participant, participant_id)
        if p is None:
            raise ApiError(404, f"no participant {participant_id}")
        if p.excluded_at is None:
            raise ApiError(409, f"participant {participant_id} is not excluded")
        p.excluded_at = None
        p.exclusion_reason = None
        s.add(
            StatusChange(
                participant_id=p.id, status=ExclusionMark.INCLUDED, at=utcnow(), note=reason
            )
        )
    with state.db.read() as s:
        return _participant_detail(s, participant_id)


@router.post("/participants/{participant_id}/erasure", response_model=Erased)
def erase(participant_id: RowId, state: StateDep) -> Erased:
    """Erase the participant on their request: every row of theirs, in every table, in one
    transaction; one audit row (``erasures.csv``) keeps when, the pseudonyms and the counts."""
    secret = state.settings.secret.get_secret_value() if state.settings.secret else None
    return erase_participant(state.db, participant_id, ErasedBy.EXPERIMENTER, secret)


@router.post("/participants/{participant_id}/approval", response_model=AdminParticipantDetail)
def approve(participant_id: RowId, body: ReviewRequest, state: StateDep) -> AdminParticipantDetail:
    """Approve the participant's submitted work on their platform (``BAM_REVIEW_BACKEND``),
    once; a repeat answers the same."""
    return _decide(participant_id, ReviewDecision.APPROVED, body, state)


@router.post("/approvals", response_model=BulkApprovalView)
def approve_many(body: BulkApprovalRequest, state: StateDep) -> BulkApprovalView:
    """Approve several participants' submitted work: each as its own approval (recorded before
    the platform's call, once; a repeat answers the same), so that one refusal (a participant
    rejected before, or not submitted) stops none of the others."""
    approved: list[int] = []
    refused: dict[int, str] = {}
    for participant_id in dict.fromkeys(body.participant_ids):
        try:
            _decide(
                participant_id, ReviewDecision.APPROVED, ReviewRequest(message=body.message), state
            )
        except ApiError as error:
            refused[participant_id] = error.message
        else:
            approved.append(participant_id)
    return BulkApprovalView(approved=approved, refused=refused)


@router.post("/participants/{participant_id}/rejection", response_model=AdminParticipantDetail)
def reject(participant_id: RowId, body: ReviewRequest, state: StateDep) -> AdminParticipantDetail:
    """Reject the participant's submitted work, with a message (on Prolific: a category and a
    message of at least 100 characters), once."""
    return _decide(participant_id, ReviewDecision.REJECTED, body, state)


def _backend_for(state: ServerState, participant_id: int) -> review.ReviewBackend:
    with state.db.read() as s:
        p = s.get(Participant, participant_id)
        if p is None:
            raise ApiError(404, f"no participant {participant_id}")
        platform = p.platform
    return state.review_backend(platform)


def _decide(
    participant_id: int, decision: ReviewDecision, body: ReviewRequest, state: ServerState
) -> AdminParticipantDetail:
    backend = _backend_for(state, participant_id)
    review.review_submission(
        state.db, backend, participant_id, decision, body.message, body.rejection_category
    )
    with state.db.read() as s:
        return _participant_detail(s, participant_id)


@router.post("/reconciliation")
def reconcile(
    state: StateDep,
    prolific_study: Annotated[
        str | None,
        Query(
            pattern=r"^[0-9a-f]{24}$", description="Also poll this Prolific study's submissions."
        ),
    ] = None,
) -> dict[str, Any]:
    """Settle the unsettled bonuses that can be settled without paying twice (MTurk's by their
    UniqueRequestToken; Prolific's set up but never sent to pay, and Prolific's in doubt from
    the submission's ``bonus_payments``), and, with ``prolific_study``,
    apply Prolific's status of each of the study's submissions (for a server that Prolific's
    webhook cannot reach)."""
    settled: list[str] = []
    with state.db.read() as s:
        platforms = set(
            s.scalars(
                select(Participant.platform)
                .join(Bonus, Bonus.participant_id == Participant.id)
                .where(Bonus.state.in_(review.UNSETTLED))
            )
        )
    for platform in sorted(platforms):
        settled += review.reconcile_bonuses(state.db, state.review_backend(platform))
    statuses: dict[str, str] = {}
    if prolific_study is not None:
        backend = state.review_backend("prolific")
        client = getattr(backend, "client", None)
        if client is None:
            raise ApiError(409, "the review backend for Prolific has no Prolific client")
        try:
            statuses = prolific_sync.reconcile_submissions(state.db, client, prolific_study)
        except review.ReviewRefused as refused:
            raise ApiError(409, str(refused)) from None
        except review.ReviewUnavailable as error:
            raise ApiError(502, str(error)) from None
    return {"settled_bonuses": settled, "prolific_statuses": statuses}


@router.post("/participants/{participant_id}/bonuses", response_model=AdminParticipantDetail)
def send_bonus(
    participant_id: RowId, body: BonusRequest, state: StateDep
) -> AdminParticipantDetail:
    """Pay the participant a bonus; a retry with the same ``unique_token`` pays nothing more
    and answers the same (a Prolific bonus in doubt is settled from Prolific's record first); a
    bonus past the study file's budget for the platform's bonuses is refused (409)."""
    backend = _backend_for(state, participant_id)
    review.pay_bonus(
        state.db,
        backend,
        participant_id,
        body.amount,
        body.reason,
        body.unique_token,
        registry.platform(backend.platform).bonus_budget_cents(state.study),
    )
    with state.db.read() as s:
        return _participant_detail(s, participant_id)


@router.get("/servers", response_model=list[ServerRow])
async def read_servers(state: StateDep) -> list[ServerRow]:
    """The deployment's servers (several ``serve`` processes on one PostgreSQL database), the
    latest started first: every live one, and the latest ten gone, each with its heartbeat and
    its load."""
    lease = state.settings.update_lease_seconds
    this = state.updates.server if state.updates is not None else None
    found = await state.run_db(lambda: deployment_servers(state.db, lease))
    shown = [row for row in found if row.live] + [row for row in found if not row.live][:10]
    return [
        ServerRow(
            name=row.name,
            host=row.host,
            pid=row.pid,
            started_at=row.started_at,
            heartbeat_at=row.heartbeat_at,
            stopped_at=row.stopped_at,
            live=row.live,
            this_server=row.name == this,
            **vars(row.load),
        )
        for row in shown
    ]


@router.get("/queue", response_model=QueueView)
async def read_queue(state: StateDep) -> QueueView:
    """The learner updates' live queue (updates pending, the oldest wait, participants in the
    study and waiting) beside the capacity and the limit of participants at once."""
    queue = state.updates.queue() if state.updates is not None else None  # on its own loop
    return await state.run_db(lambda: places.queue_view(state, queue))


@router.get("/sessions", response_model=list[AdminSession])
def list_sessions(
    state: StateDep,
    live: Annotated[bool, Query(description="Only sessions being taught now.")] = False,
) -> list[AdminSession]:
    """Learning sessions with progress, pending updates and latest normalised return."""
    with state.db.read() as s:
        query = select(LearningSession).order_by(LearningSession.id)
        if live:
            query = query.join(Participant).where(
                LearningSession.status == SessionStatus.ACTIVE, Participant.status.in_(IN_PROGRESS)
            )
        return _admin_sessions(s, list(s.scalars(query)))


def _session(s: Session, session_id: int) -> LearningSession:
    session = s.get(LearningSession, session_id)
    if session is None:
        raise ApiError(404, f"no learning session {session_id}")
    return session


@router.get("/sessions/{session_id}/evaluations", response_model=list[AdminEvaluation])
def list_evaluations(session_id: RowId, state: StateDep) -> list[AdminEvaluation]:
    """The session's learning curve: normalised return after each update."""
    with state.db.read() as s:
        _session(s, session_id)
        rows = s.execute(
            select(
                LearnerUpdate.update_index,
                LearnerUpdate.status,
                LearnerUpdate.episodes,
                LearnerUpdate.actions,
                LearnerUpdate.normalized_return,
                LearnerUpdate.seconds,
                LearnerUpdate.queued_at,
                LearnerUpdate.finished_at,
            )
            .where(LearnerUpdate.session_id == session_id)
            .order_by(LearnerUpdate.update_index)
        ).all()
    return [AdminEvaluation(**row._asdict()) for row in rows]


@router.get("/sessions/{session_id}/replay", response_model=AdminReplay)
def replay(session_id: RowId, state: StateDep) -> AdminReplay:
    """What a replay needs: the grid, the first state and every event of the session."""
    with state.db.read() as s:
        session = _session(s, session_id)
        events = s.scalars(
            select(Event).where(Event.session_id == session_id).order_by(Event.id)
        ).all()
        summary = _admin_sessions(s, [session])[0]
    return AdminReplay(
        session=summary,
        environment=teaching.environment_description(session.environment, reveal_gravity=True),
        start_state=assignment.initial_state(session) if session.started_at else None,
        events=[
            AdminEvent(
                event_id=e.id,
                seq=e.seq,
                kind=e.kind,
                created_at=e.created_at,
                task=e.task,
                mode=e.mode,
                state=e.state,
                action=e.action,
                next_state=e.next_state,
                feedback=e.feedback,
                episode_index=e.episode_index,
                record=e.record,
                stay_state=e.stay_state,
                episode_end=e.episode_end,
            )
            for e in events
        ],
    )


@router.get("/participants/{participant_id}/quality")
def read_quality(participant_id: RowId, state: StateDep) -> dict[str, Any]:
    """The participant's row of ``quality.csv``: the quality checks, their flags and the
    Prolific ground they support, if any (404 until the participant has completed)."""
    quality = export_tables(state.db)["quality"]
    rows = quality[quality["participant_id"] == participant_id]
    if rows.empty:
        raise ApiError(404, f"no quality checks for participant {participant_id} (not completed)")
    row = rows.iloc[0].astype(object).where(rows.iloc[0].notna(), None)
    return {name: value.item() if hasattr(value, "item") else value for name, value in row.items()}


@router.get(
    "/export.zip",
    response_class=Response,
    responses={200: {"content": {"application/zip": {}}}},
)
def download_export(
    state: StateDep,
    pseudonymize: Annotated[bool, Query(description="Hash worker and assignment ids.")] = True,
) -> Response:
    """The export (CSV files and their data dictionary) as a zip."""
    secret = state.settings.secret.get_secret_value() if state.settings.secret else None
    tables = export_tables(state.db, pseudonymize=pseudonymize, secret=secret)
    stamp = utcnow().strftime("%Y%m%dT%H%M%SZ")
    return Response(
        content=export_zip(tables),
        media_type="application/zip",
        headers={"Content-Disposition": f'attachment; filename="bam-study-export-{stamp}.zip"'},
    )


@router.get("/mturk-replica", response_model=ReplicaRecords)
def mturk_replica(state: StateDep) -> ReplicaRecords:
    """The MTurk replica's assignments and every submission it recorded."""
    with state.db.read() as s:
        assignments = s.scalars(select(ReplicaAssignment).order_by(ReplicaAssignment.id)).all()
        submissions = s.scalars(select(ReplicaSubmission).order_by(ReplicaSubmission.id)).all()
    return ReplicaRecords(
        assignments=[
            ReplicaAssignmentView(
                row=a.id,
                hit_id=a.hit_id,
                assignment_id=a.assignment_id,
                worker_id=a.worker_id,
                status=a.status,
                accepted_at=a.accepted_at,
                returned_at=a.returned_at,
                submitted_at=a.submitted_at,
            )
            for a in assignments
        ],
        submissions=[
            ReplicaSubmissionView(
                assignment_id=x.assignment_id,
                worker_id=x.worker_id,
                hit_id=x.hit_id,
                fields=x.fields,
                submitted_at=x.submitted_at,
            )
            for x in submissions
        ],
    )


@router.get("/prolific-studies", response_model=list[ProlificStudyView])
def prolific_studies(state: StateDep) -> list[ProlificStudyView]:
    """Each Prolific study with an event or a participant of ours: Prolific's status of it
    (``study.status.change``) and its high-return-rate warning, beside our count of returns."""
    with state.db.read() as s:
        known = {row.study_id: row for row in s.scalars(select(ProlificStudy))}
        ids = set(known) | set(
            s.scalars(
                select(Participant.platform_study_id).where(
                    Participant.platform == "prolific", Participant.platform_study_id.is_not(None)
                )
            )
        )
        views = []
        for study_id in sorted(i for i in ids if i):
            row = known.get(study_id)
            warning = None
            if row is not None and row.high_return_rate_at is not None:
                counts = prolific_sync.returns_of(s, study_id)
                arrived, returned = counts.pop("arrived"), counts.pop("returned")
                warning = HighReturnRateView(
                    warned_at=row.high_return_rate_at,
                    metadata=dict(row.high_return_rate_metadata or {}),
                    arrived=arrived,
                    returned=returned,
                    share_returned=returned / arrived if arrived else None,
                    reasons=counts,
                )
            views.append(
                ProlificStudyView(
                    study_id=study_id,
                    status=row.status if row else None,
                    status_at=row.status_at if row else None,
                    high_return_rate=warning,
                    changes=[
                        ProlificStudyChangeView(
                            at=c.at,
                            change=c.change,
                            value=c.value,
                            reason=c.reason,
                            outcome=c.outcome,
                        )
                        for c in prolific_capacity.changes_of(state.db, study_id)
                    ],
                )
            )
    return views
