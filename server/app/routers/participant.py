"""The participant's own state and the steps of the flow outside teaching."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict

from fastapi import APIRouter, Request, Response

from server.app.deps import StateDep, TokenDep
from server.app.errors import ApiError
from server.app.participants import (
    assignment,
    attention,
    completion,
    device,
    places,
    tokens,
    transaction,
    views,
)
from server.app.participants.transaction import Transaction
from server.app.rights.withdrawal import Withdrawal, withdraw
from server.app.routers.common import answer
from server.app.schemas import (
    AttentionMoveRequest,
    AttentionOutcome,
    Completion,
    ConsentRequest,
    DeviceCheckRequest,
    Outcome,
    ParticipantState,
    PlaceView,
    QuestionnaireRequest,
    RequestOutcome,
    SeqRequest,
    TutorialStepRequest,
)
from server.app.state import ServerState

router = APIRouter(prefix="/api/participant", tags=["participants"])


async def perform(
    state: ServerState,
    token: str | None,
    kind: str,
    body: SeqRequest,
    handler: Callable[[Transaction], RequestOutcome | AttentionOutcome],
) -> Response:
    return answer(
        state, await state.run_db(lambda: transaction.perform(state, token, kind, body, handler))
    )


def participant_response(transaction: Transaction) -> RequestOutcome:
    transaction.flush()
    current = views.current_session_id(transaction.c, transaction.participant)
    return RequestOutcome(
        seq=transaction.seq,
        kind=transaction.event["kind"],
        outcome=Outcome(),
        session=None,
        participant=views.brief(transaction.participant, transaction.study, current),
    )


@router.get("", response_model=ParticipantState)
async def read_participant(state: StateDep, token: TokenDep) -> ParticipantState:
    """Where the participant is: status, sessions, the current one, the next seq."""

    def read() -> ParticipantState:
        with state.db.connect() as c:
            participant = tokens.participant_for(c, token)
            return views.participant_state(c, participant, state.study)

    return await state.run_db(read)


@router.post("/place", response_model=PlaceView)
async def ask_for_place(state: StateDep, token: TokenDep) -> PlaceView:
    """A participant who arrived while the study was full asks for a place: in as soon as one
    is free for them (the first in line first); anyone else is in already."""

    def ask() -> PlaceView:
        with state.db.connect() as c:
            participant = tokens.participant_for(c, token)
        place = places.admit(
            state.db, participant.id, places.study_limit(state), state.settings.active_minutes
        )
        return PlaceView(**asdict(place), ask_seconds=places.ASK_SECONDS)

    return await state.run_db(ask)


@router.post("/device-check", response_model=RequestOutcome)
async def device_check(
    body: DeviceCheckRequest, request: Request, state: StateDep, token: TokenDep
) -> Response:
    """Before consent (a study with ``[device_check]``): what the page measured. A device that
    cannot take part turns the participant away (status incompatible; on Prolific the answer's
    completion has the study's INCOMPATIBLE_DEVICE code); one that can stays at consent."""
    browser = device.browser_name(request.headers.get("user-agent"))

    def handle(transaction: Transaction) -> RequestOutcome:
        device.check_device(transaction, body, browser)
        return participant_response(transaction)

    return await perform(state, token, "device_check", body, handle)


@router.post("/consent", response_model=RequestOutcome)
async def consent(body: ConsentRequest, state: StateDep, token: TokenDep) -> Response:
    """Agree (the domain is assigned, the sessions are created) or decline (the flow ends)."""

    def handle(transaction: Transaction) -> RequestOutcome:
        assignment.consent(transaction, body.agree)
        return participant_response(transaction)

    return await perform(state, token, "consent", body, handle)


@router.post("/start", response_model=RequestOutcome)
async def start(body: SeqRequest, state: StateDep, token: TokenDep) -> Response:
    """After the instructions: the tutorial (or the first agent) begins."""

    def handle(transaction: Transaction) -> RequestOutcome:
        assignment.start(transaction)
        return participant_response(transaction)

    return await perform(state, token, "start", body, handle)


@router.post("/tutorial", response_model=RequestOutcome)
async def tutorial_step(body: TutorialStepRequest, state: StateDep, token: TokenDep) -> Response:
    """The tutorial step the participant reached, kept so that it continues in any browser."""

    def handle(transaction: Transaction) -> RequestOutcome:
        completion.reach_tutorial_step(transaction, body.step)
        return participant_response(transaction)

    return await perform(state, token, "tutorial", body, handle)


@router.post("/attention-check/move", response_model=AttentionOutcome)
async def attention_move(body: AttentionMoveRequest, state: StateDep, token: TokenDep) -> Response:
    """An arrow in the attention check being taken (409 when none is): the server moves the
    robot and decides whether the check is passed (the star reached) or failed (the moves
    allowed used up); either ends it, and the next agent begins."""

    def handle(transaction: Transaction) -> AttentionOutcome:
        check = attention.move(transaction, body.action)
        transaction.flush()
        current = views.current_session_id(transaction.c, transaction.participant)
        return AttentionOutcome(
            seq=transaction.seq,
            kind=transaction.event["kind"],
            check=attention.view(transaction.c, check),
            participant=views.brief(transaction.participant, transaction.study, current),
        )

    return await perform(state, token, "attention_move", body, handle)


@router.post("/questionnaire", response_model=RequestOutcome)
async def questionnaire(body: QuestionnaireRequest, state: StateDep, token: TokenDep) -> Response:
    """The answers to the post-study questionnaire (the study file's ``[questionnaire]``); the
    completion code is issued with them. 422 (nothing stored) for a required question left
    unanswered, a choice not offered or a Likert point off the scale."""

    def handle(transaction: Transaction) -> RequestOutcome:
        completion.answer_questionnaire(transaction, body.answers)
        return participant_response(transaction)

    return await perform(state, token, "questionnaire", body, handle)


@router.get("/completion", response_model=Completion)
async def read_completion(state: StateDep, token: TokenDep) -> Completion:
    """The completion code, once the completion is committed (409 before)."""

    def read() -> Completion:
        with state.db.connect() as c:
            participant = tokens.participant_for(c, token)
            code = completion.completion(participant, state.study)
        if code is None:
            raise ApiError(409, f"the study is not completed yet (status {participant.status})")
        return code

    return await state.run_db(read)


@router.post("/submission", response_model=RequestOutcome)
async def record_submission(body: SeqRequest, state: StateDep, token: TokenDep) -> Response:
    """The page is sending the submission to the platform (MTurk's form, Prolific's redirect)."""

    def handle(transaction: Transaction) -> RequestOutcome:
        completion.submission(transaction)
        return participant_response(transaction)

    return await perform(state, token, "submission", body, handle)


@router.post("/withdrawal", response_model=Withdrawal)
async def withdrawal(state: StateDep, token: TokenDep, response: Response) -> Withdrawal:
    """Stop and delete my data: every row of the participant is erased (one audit row without
    personal data is kept); the answer says how to leave the platform. The cookie is cleared."""
    secret = state.settings.secret.get_secret_value() if state.settings.secret else None
    done = await state.run_db(lambda: withdraw(state.db, token, state.study, secret))
    response.delete_cookie(state.settings.cookie_name)
    return done
