"""Teaching one learning session: task, mode, moves, agent steps, feedback, resets, episodes.

Each function is the handler of one request (run by ``transaction.perform`` in the request's
transaction). What the learner observes is written on the request's event (``record``); the
update worker replays those events in order, so the database is the learner's only input.

Episodes: the first demonstrated move (demonstrate mode) or agent step (agent mode) opens one.
It ends when the participant ends it (a demonstration then gets its synthetic STAY), when a
demonstration reaches the selected task's goal (with its STAY), when an agent episode reaches the
goal or the horizon, or implicitly when the participant changes mode or task, resets, or finishes
the agent (no STAY: the demonstration was abandoned, not completed). Each ended episode queues
one learner update. An episode end by the participant, the goal or the horizon stops the agent
(mode idle): the participant is then prompted to reset.

No episode starts on the selected task's goal: there the task is done already, so a try would
end at its first step (and count as an episode, with an update) and a demonstration would show a
move away from the goal. Turning a mode on (demonstrate or let the agent try), or selecting a
task while one is on, with the agent on that task's goal first puts the agent at a random start
of the task, as Reset does (``Outcome.new_start``); Reset never draws the goal itself.
"""

from __future__ import annotations

from functools import cache
from typing import Any

from sqlalchemy import Connection, bindparam, update

from server.app.errors import ApiError, LearnerBusy
from server.app.participants import assignment, views
from server.app.participants.transaction import Transaction
from server.app.schemas import (
    EpisodeState,
    Learning,
    Outcome,
    RequestOutcome,
    SessionView,
    TeachingState,
)
from server.app.storage.records import Record, add, get
from server.app.storage.tables import EPISODES, SESSIONS
from server.app.storage.vocabulary import (
    EpisodeEnd,
    EpisodeKind,
    LastAction,
    Mode,
    Observed,
    SessionKind,
    SessionStatus,
)
from server.domains import make as make_environment
from server.domains.base import ACTIONS, STAY, Environment

ACTION_INDEX = {name: index for index, name in enumerate(ACTIONS)}
_END_EPISODE = (
    update(EPISODES)
    .where(
        EPISODES.c.session_id == bindparam("of_session"),
        EPISODES.c.index == bindparam("of_episode"),
    )
    .values(
        ended_at=bindparam("new_ended_at"),
        end_state=bindparam("new_end_state"),
        end_reason=bindparam("new_end_reason"),
        actions=bindparam("new_actions"),
        update_index=bindparam("new_update_index"),
    )
)


@cache
def environment_description(name: str, reveal_gravity: bool = False) -> dict[str, Any]:
    """The static drawing of the grid (shared: do not change it). The hidden effect of gravity
    colours is left out unless the study reveals it: participants discover it by watching, as
    the learner does."""
    description = make_environment(name).describe()
    if not reveal_gravity:
        description.pop("gravity_of_colour", None)
    return description


def own_session(c: Connection, participant: Any, session_id: int) -> Record:
    """The participant's session ``session_id`` (404 if there is none of theirs)."""
    session = get(c, SESSIONS, session_id)
    if session is None or session.participant_id != participant.id:
        raise ApiError(404, f"no learning session {session_id} for this participant")
    return session


def session_for(transaction: Transaction, session_id: int) -> Record:
    """The participant's session ``session_id`` being taught, tracked for writing back."""
    session = own_session(transaction.c, transaction.participant, session_id)
    if session.status == SessionStatus.PENDING:
        raise ApiError(409, "this agent's turn has not come yet")
    if session.status == SessionStatus.FINISHED:
        raise ApiError(409, "this agent is finished: go on with the next one")
    return transaction.track(session)


def teaching_state(session: Any, env: Environment) -> TeachingState:
    missing = [env.tasks[k].name for k, n in enumerate(session.demonstrated) if n == 0]
    blocked = None
    if session.status != SessionStatus.ACTIVE:
        blocked = "this agent is not being taught"
    elif session.kind == SessionKind.STUDY and missing:
        blocked = (
            f"every task needs at least one demonstrated move first; not yet: {', '.join(missing)}"
        )
    episode = None
    if session.open_episode is not None:
        episode = EpisodeState(
            index=session.open_episode,
            kind=EpisodeKind.DEMONSTRATION
            if session.mode == Mode.DEMONSTRATE
            else EpisodeKind.AGENT,
            task=session.task,
            actions=session.episode_actions,
        )
    return TeachingState(
        session_id=session.id,
        status=session.status,
        task=session.task,
        mode=session.mode,
        agent=env.describe_state(session.state) if session.state is not None else None,
        episode=episode,
        episodes=session.episodes,
        actions=session.actions,
        demonstrated=list(session.demonstrated),
        can_finish=blocked is None,
        finish_blocked=blocked,
        can_give_feedback=session.last_action == LastAction.AGENT,
        learning=learning(session),
    )


def learning(session: Any) -> Learning:
    return Learning(
        pending=max(0, session.updates_requested - session.updates_processed),
        updates=session.updates_processed,
    )


def respond(
    transaction: Transaction, session: Record, outcome: Outcome, current: int | None = None
) -> RequestOutcome:
    env = make_environment(session.environment)
    if current is None:
        current = session.id if session.status == SessionStatus.ACTIVE else None
    return RequestOutcome(
        seq=transaction.seq,
        kind=transaction.event["kind"],
        outcome=outcome,
        session=teaching_state(session, env),
        participant=views.brief(transaction.participant, transaction.study, current),
    )


def session_view(c: Connection, participant: Any, study: Any, session_id: int) -> SessionView:
    session = own_session(c, participant, session_id)
    env = make_environment(session.environment)
    current = (
        session.id
        if session.status == SessionStatus.ACTIVE
        else views.current_session_id(c, participant)
    )
    return SessionView(
        summary=views.summary(session),
        environment=environment_description(session.environment, study.reveal_gravity),
        teaching=teaching_state(session, env),
        participant=views.brief(participant, study, current),
    )


# -- episodes -------------------------------------------------------------------------------
def _observe(transaction: Transaction, session: Record, record: Observed, **columns: Any) -> None:
    """What the learner observes from this request (see ``updates.records_of``)."""
    transaction.event.update(record=record, task=session.task, **columns)


def _open_episode(transaction: Transaction, session: Record, kind: EpisodeKind) -> None:
    if session.open_episode is not None:
        return
    session.open_episode = session.episodes
    session.episode_actions = 0
    add(
        transaction.c,
        EPISODES,
        session_id=session.id,
        index=session.open_episode,
        kind=kind,
        task=session.task,
        start_state=session.state,
        started_at=transaction.now,
    )


def close_episode(
    transaction: Transaction, session: Record, env: Environment, reason: EpisodeEnd, stay: bool
) -> int | None:
    """End the open episode (if any) and queue the learner's update; returns its index."""
    if session.open_episode is None:
        return None
    event = transaction.event
    if stay and session.mode == Mode.DEMONSTRATE:
        # The synthetic STAY: people cannot demonstrate staying at the goal.
        event["stay_state"] = env.step(session.state, STAY, transaction.rng(session.seed))
        event["task"] = session.task
        session.state = event["stay_state"]
    event["episode_end"] = reason
    event["episode_index"] = session.open_episode
    session.episodes += 1
    session.updates_requested += 1
    transaction.c.execute(
        _END_EPISODE,
        {
            "of_session": session.id,
            "of_episode": session.open_episode,
            "new_ended_at": transaction.now,
            "new_end_state": session.state,
            "new_end_reason": reason,
            "new_actions": session.episode_actions,
            "new_update_index": session.updates_requested,
        },
    )
    session.open_episode = None
    session.episode_actions = 0
    return transaction.queue_update(session)


def _leave_goal(transaction: Transaction, session: Record, env: Environment) -> bool:
    """With a mode on and no episode open, an agent on the selected task's goal goes to a
    random start of the task first (module docstring); returns whether it did."""
    if session.mode == Mode.IDLE or session.open_episode is not None:
        return False
    if not env.is_goal(session.task, int(session.state)):
        return False
    session.state = assignment.random_start(env.name, session.task, transaction.rng(session.seed))
    session.last_action = None
    return True


def _switched(
    transaction: Transaction, session: Record, env: Environment, state: int, queued: int | None
) -> RequestOutcome:
    """The answer to a task or mode change (from ``state``), once the agent is off the goal."""
    moved = _leave_goal(transaction, session, env)
    transaction.event.update(
        task=session.task, mode=session.mode, state=state, next_state=session.state
    )
    return respond(
        transaction,
        session,
        Outcome(
            episode_ended=transaction.event.get("episode_end"),
            update_queued=queued,
            new_start=moved,
            state=state if moved else None,
            next_state=session.state if moved else None,
        ),
    )


# -- handlers -------------------------------------------------------------------------------
def set_task(transaction: Transaction, session_id: int, task: int) -> RequestOutcome:
    session = session_for(transaction, session_id)
    env = make_environment(session.environment)
    if task >= len(env.tasks):
        raise ApiError(400, f"task {task} does not exist here: tasks are 0..{len(env.tasks) - 1}")
    state = int(session.state)
    queued = None
    if task != session.task:
        queued = close_episode(transaction, session, env, EpisodeEnd.TASK, stay=False)
        session.task = task
        session.last_action = None  # feedback belongs to the task selected when it is given
    return _switched(transaction, session, env, state, queued)


def set_mode(transaction: Transaction, session_id: int, mode: Mode) -> RequestOutcome:
    session = session_for(transaction, session_id)
    env = make_environment(session.environment)
    state = int(session.state)
    queued = None
    if mode != session.mode:
        queued = close_episode(transaction, session, env, EpisodeEnd.MODE, stay=False)
        session.mode = mode
    return _switched(transaction, session, env, state, queued)


def move(transaction: Transaction, session_id: int, name: str) -> RequestOutcome:
    """An arrow key: a demonstrated action (demonstrate mode) or a move alone (idle mode)."""
    session = session_for(transaction, session_id)
    if session.mode == Mode.AGENT:
        raise ApiError(409, "the agent is acting on its own: stop it before moving it")
    env = make_environment(session.environment)
    act = ACTION_INDEX[name]
    state = int(session.state)
    next_state = env.step(state, act, transaction.rng(session.seed))
    transaction.event.update(mode=session.mode, state=state, action=act, next_state=next_state)
    outcome = Outcome(state=state, action=name, next_state=next_state)
    if session.mode == Mode.IDLE:
        session.state = next_state
        _observe(transaction, session, Observed.IDLE_MOVE)
        session.idle_moves += 1
        session.last_action = LastAction.IDLE
        return respond(transaction, session, outcome)
    _open_episode(
        transaction, session, EpisodeKind.DEMONSTRATION
    )  # starts where the first move starts
    session.state = next_state
    _observe(transaction, session, Observed.DEMONSTRATION, episode_index=session.open_episode)
    session.episode_actions += 1
    session.actions += 1
    demonstrated = list(session.demonstrated)
    demonstrated[session.task] += 1
    session.demonstrated = demonstrated
    session.last_action = LastAction.DEMONSTRATION
    if env.is_goal(session.task, next_state):
        outcome.goal_reached = True
        outcome.update_queued = close_episode(transaction, session, env, EpisodeEnd.GOAL, stay=True)
        outcome.episode_ended = EpisodeEnd.GOAL
        session.mode = Mode.IDLE
    return respond(transaction, session, outcome)


def agent_step(transaction: Transaction, session_id: int) -> RequestOutcome:
    """One step of the agent on its learner's greedy policy (waits for its pending update)."""
    session = session_for(transaction, session_id)
    if session.mode != Mode.AGENT:
        raise ApiError(409, "let the agent try first (mode agent)")
    if session.updates_processed < session.updates_requested:
        raise LearnerBusy(session.id, session.updates_requested)
    if session.policy_update is None:
        raise ApiError(503, "this agent's learner failed to start; please tell the researchers")
    env = make_environment(session.environment)
    policy = transaction.server.policies.get(transaction.c, session, env)
    state = int(session.state)
    act = int(policy[session.task, state])
    next_state = env.step(state, act, transaction.rng(session.seed))
    _open_episode(transaction, session, EpisodeKind.AGENT)
    transaction.event.update(mode=session.mode, state=state, action=act, next_state=next_state)
    _observe(
        transaction, session, Observed.AGENT_STEP, feedback=0, episode_index=session.open_episode
    )
    session.state = next_state
    session.episode_actions += 1
    session.actions += 1
    session.last_action = LastAction.AGENT
    outcome = Outcome(state=state, action=ACTIONS[act], next_state=next_state)
    reason = None
    if env.is_goal(session.task, next_state):
        outcome.goal_reached = True
        reason = EpisodeEnd.GOAL
    elif session.episode_actions >= env.horizon:
        reason = EpisodeEnd.HORIZON
    if reason is not None:
        outcome.update_queued = close_episode(transaction, session, env, reason, stay=False)
        outcome.episode_ended = reason
        session.mode = Mode.IDLE
    return respond(transaction, session, outcome)


def feedback(transaction: Transaction, session_id: int, value: int) -> RequestOutcome:
    session = session_for(transaction, session_id)
    if session.last_action != LastAction.AGENT:
        raise ApiError(409, "there is no agent action to give feedback on")
    _observe(transaction, session, Observed.FEEDBACK, feedback=value)
    transaction.event.update(mode=session.mode, state=session.state, next_state=session.state)
    return respond(transaction, session, Outcome(feedback=value))


def reset(transaction: Transaction, session_id: int) -> RequestOutcome:
    """A random start of the selected task (the study's start distribution, never its goal)."""
    session = session_for(transaction, session_id)
    env = make_environment(session.environment)
    queued = close_episode(transaction, session, env, EpisodeEnd.RESET, stay=False)
    state = int(session.state)
    session.state = assignment.random_start(env.name, session.task, transaction.rng(session.seed))
    session.last_action = None
    transaction.event.update(
        task=session.task, mode=session.mode, state=state, next_state=session.state
    )
    return respond(
        transaction,
        session,
        Outcome(
            state=state,
            next_state=session.state,
            episode_ended=transaction.event.get("episode_end"),
            update_queued=queued,
        ),
    )


def end_episode(transaction: Transaction, session_id: int) -> RequestOutcome:
    """The participant ends the episode (Stop); a demonstration gets its synthetic STAY."""
    session = session_for(transaction, session_id)
    if session.open_episode is None:
        raise ApiError(409, "no episode in progress")
    env = make_environment(session.environment)
    transaction.event.update(
        state=session.state, next_state=session.state, task=session.task, mode=Mode.IDLE
    )
    queued = close_episode(transaction, session, env, EpisodeEnd.END, stay=True)
    session.mode = Mode.IDLE
    return respond(
        transaction, session, Outcome(episode_ended=EpisodeEnd.END, update_queued=queued)
    )


def open_session(transaction: Transaction, session_id: int) -> RequestOutcome:
    """Past the agent's introduction page (a reload before this shows that page again)."""
    session = session_for(transaction, session_id)
    if session.opened_at is None:
        session.opened_at = transaction.now
    transaction.event.update(
        state=session.state, next_state=session.state, task=session.task, mode=session.mode
    )
    return respond(transaction, session, Outcome())


def finish_session(transaction: Transaction, session_id: int) -> RequestOutcome:
    """Finish this agent (only once every task has a demonstrated action) and go on."""
    session = session_for(transaction, session_id)
    env = make_environment(session.environment)
    state = teaching_state(session, env)
    if not state.can_finish:
        raise ApiError(409, f"cannot finish this agent yet: {state.finish_blocked}")
    transaction.event.update(
        state=session.state, next_state=session.state, task=session.task, mode=session.mode
    )
    queued = close_episode(transaction, session, env, EpisodeEnd.FINISH, stay=False)
    session.status = SessionStatus.FINISHED
    session.finished_at = transaction.now
    session.completed = True
    session.mode = Mode.IDLE
    following = assignment.advance(transaction, session)
    return respond(
        transaction,
        session,
        Outcome(episode_ended=transaction.event.get("episode_end"), update_queued=queued),
        current=following.id if following is not None else None,
    )
