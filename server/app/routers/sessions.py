"""Teaching one learning session (one agent). Every POST carries the participant's next ``seq``.

The agent step is the one request that may wait: for its own learner's pending update (never
for other participants' updates), up to ``BAM_AGENT_WAIT_SECONDS``, then 503 with Retry-After.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Annotated

from fastapi import APIRouter, Query, Response

from server.app.deps import RowId, StateDep, TokenDep
from server.app.errors import ApiError, LearnerBusy
from server.app.participants import teaching, tokens, transaction
from server.app.participants.transaction import Transaction
from server.app.routers.common import answer
from server.app.schemas import (
    FeedbackRequest,
    Learning,
    ModeRequest,
    MoveRequest,
    RequestOutcome,
    SeqRequest,
    SessionView,
    TaskRequest,
)
from server.app.state import ServerState
from server.app.storage.vocabulary import Mode

router = APIRouter(prefix="/api/sessions", tags=["teaching"])


async def teach(
    state: ServerState,
    token: str | None,
    kind: str,
    body: SeqRequest,
    session_id: int,
    handler: Callable[[Transaction], RequestOutcome],
) -> Response:
    performed = await state.run_db(
        lambda: transaction.perform(state, token, kind, body, handler, session_id)
    )
    return answer(state, performed)


@router.get("/{session_id}", response_model=SessionView)
async def read_session(session_id: RowId, state: StateDep, token: TokenDep) -> SessionView:
    """Everything to draw the session: the grid, the agent, the mode, the task, progress."""

    def read() -> SessionView:
        with state.db.connect() as c:
            participant = tokens.participant_for(c, token)
            return teaching.session_view(c, participant, state.study, session_id)

    return await state.run_db(read)


@router.get("/{session_id}/learning", response_model=Learning)
async def read_learning(
    session_id: RowId,
    state: StateDep,
    token: TokenDep,
    wait: Annotated[
        float,
        Query(
            ge=0,
            le=60,
            allow_inf_nan=False,
            description="Wait up to this long for the agent to learn.",
        ),
    ] = 0.0,
) -> Learning:
    """Whether the agent is learning (pending updates), optionally waiting until it is done."""

    def read() -> tuple[Learning, bool]:
        with state.db.connect() as c:
            participant = tokens.participant_for(c, token)
            session = teaching.own_session(c, participant, session_id)
            return teaching.learning(session), session.mode == Mode.AGENT

    learning, agent_mode = await state.run_db(read)
    if learning.pending and wait > 0 and state.updates is not None:
        # In agent mode the participant waits for the agent; otherwise the page only follows.
        await state.updates.wait(session_id, awaited_update(learning), wait, awaited=agent_mode)
        learning, _ = await state.run_db(read)
    return learning


def awaited_update(learning: Learning) -> int:
    """The index of the session's last update requested (the one its agent will be)."""
    return learning.updates + learning.pending


@router.post("/{session_id}/task", response_model=RequestOutcome)
async def select_task(
    session_id: RowId, body: TaskRequest, state: StateDep, token: TokenDep
) -> Response:
    """Select the task that demonstrations and feedback belong to (ends an open episode)."""
    return await teach(
        state, token, "task", body, session_id,
        lambda transaction: teaching.set_task(transaction, session_id, body.task),
    )  # fmt: skip


@router.post("/{session_id}/mode", response_model=RequestOutcome)
async def select_mode(
    session_id: RowId, body: ModeRequest, state: StateDep, token: TokenDep
) -> Response:
    """Demonstrate, let the agent try, or idle (ends an open episode)."""

    def handle(transaction: Transaction) -> RequestOutcome:
        response = teaching.set_mode(transaction, session_id, body.mode)
        learning = response.session.learning if response.session is not None else None
        if body.mode == Mode.AGENT and learning is not None and learning.pending:
            # The agent's turn is next: its pending updates are awaited from now on.
            expected.append(awaited_update(learning))
        return response

    expected: list[int] = []
    answered = await teach(state, token, "mode", body, session_id, handle)
    if expected and state.updates is not None:
        state.updates.expect(session_id, expected[-1])
    return answered


@router.post("/{session_id}/move", response_model=RequestOutcome)
async def move(session_id: RowId, body: MoveRequest, state: StateDep, token: TokenDep) -> Response:
    """An arrow key: a demonstrated transaction, or in idle mode a move that is not one."""
    return await teach(
        state, token, "move", body, session_id,
        lambda transaction: teaching.move(transaction, session_id, body.action),
    )  # fmt: skip


@router.post("/{session_id}/agent-step", response_model=RequestOutcome)
async def agent_step(
    session_id: RowId, body: SeqRequest, state: StateDep, token: TokenDep
) -> Response:
    """One action of the agent, from its learner's greedy policy, under the true dynamics."""
    waited: float | None = None

    def handle(transaction: Transaction) -> RequestOutcome:
        response = teaching.agent_step(transaction, session_id)
        response.outcome.learning_wait_seconds = waited
        return response

    try:
        return await teach(state, token, "agent_step", body, session_id, handle)
    except LearnerBusy as busy:
        if state.updates is None:
            raise ApiError(503, "learner updates are not running") from None
        started = time.perf_counter()
        done = await state.updates.wait(
            busy.session_id, busy.target, state.settings.agent_wait_seconds
        )
        waited = round(time.perf_counter() - started, 4)
        if not done:
            raise ApiError(
                503,
                "the agent is still learning from the last episode; try again in a moment",
                headers={"Retry-After": "2"},
            ) from None
    try:
        return await teach(state, token, "agent_step", body, session_id, handle)
    except LearnerBusy:
        # Another episode ended meanwhile (another tab): the client tries again.
        raise ApiError(
            503, "the agent is still learning; try again in a moment", headers={"Retry-After": "1"}
        ) from None


@router.post("/{session_id}/feedback", response_model=RequestOutcome)
async def give_feedback(
    session_id: RowId, body: FeedbackRequest, state: StateDep, token: TokenDep
) -> Response:
    """Positive (+1) or negative (-1) feedback on the agent's latest transaction."""
    return await teach(
        state, token, "feedback", body, session_id,
        lambda transaction: teaching.feedback(transaction, session_id, body.feedback),
    )  # fmt: skip


@router.post("/{session_id}/reset", response_model=RequestOutcome)
async def reset(session_id: RowId, body: SeqRequest, state: StateDep, token: TokenDep) -> Response:
    """Put the agent at a random start of the selected task (ends an open episode)."""
    return await teach(
        state, token, "reset", body, session_id,
        lambda transaction: teaching.reset(transaction, session_id),
    )  # fmt: skip


@router.post("/{session_id}/end-episode", response_model=RequestOutcome)
async def end_episode(
    session_id: RowId, body: SeqRequest, state: StateDep, token: TokenDep
) -> Response:
    """Stop: end the episode (a demonstration gets its synthetic STAY); the learner updates."""
    return await teach(
        state, token, "end_episode", body, session_id,
        lambda transaction: teaching.end_episode(transaction, session_id),
    )  # fmt: skip


@router.post("/{session_id}/open", response_model=RequestOutcome)
async def open_session(
    session_id: RowId, body: SeqRequest, state: StateDep, token: TokenDep
) -> Response:
    """The participant leaves the agent's introduction page and begins teaching it."""
    return await teach(
        state, token, "open", body, session_id,
        lambda transaction: teaching.open_session(transaction, session_id),
    )  # fmt: skip


@router.post("/{session_id}/finish", response_model=RequestOutcome)
async def finish(session_id: RowId, body: SeqRequest, state: StateDep, token: TokenDep) -> Response:
    """Finish this agent and go on to the next (refused until every task has a demonstrated
    transaction); after the last agent the completion is committed and its code returned."""
    return await teach(
        state, token, "finish", body, session_id,
        lambda transaction: teaching.finish_session(transaction, session_id),
    )  # fmt: skip
