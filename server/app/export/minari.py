"""The study's episodes as Minari datasets (``bam-study export --format minari``).

One dataset per environment taught (tutorials included: they are environments too), id
``bam-study/<environment>/participants-v0``, with every ended episode of the participants'
learning sessions: the demonstrations and the agent's tries, in the order of the sessions and
of their episodes. A demonstration that ended at the goal or by the participant carries the
synthetic STAY the learner observed as its last step (``synthetic_stay``). Per step ``infos``
(see ``INFOS``) give the feedback the learner holds on it: the latest + or - given while it was
the agent's latest step, as the learner's ``record_feedback`` keeps it. Feeding these
episodes to a learner gives it the demonstrations and agent steps the study's learner
observed, in the same order (tests/rl checks a cloning learner's parameters bit for bit).

Excluded participants are left out unless asked for; episodes still open at the export are left
out (their steps are in events.csv).
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from sqlalchemy import select

from server.app.rights.pseudonyms import database_secret, participant_pseudonyms
from server.app.storage.db import Database
from server.app.storage.models import Episode, Event, LearnerUpdate, LearningSession, Participant
from server.app.storage.vocabulary import EpisodeKind, Observed, UpdateStatus
from server.domains.base import STAY
from server.rl.datasets import Dataset, DatasetEpisode, DatasetError

DATASET_NAME = "participants"
INFOS: dict[str, str] = {
    "task": "Index of the episode's task (the Gymnasium environment's reset option 'task').",
    "kind": "demonstration (the participant moved the agent) or agent (the agent's own try).",
    "feedback": "+1 or -1: the participant's latest feedback on this step (agent steps), "
    "0 none. Entry t + 1 is the t-th action's; entry 0 (the start) is 0.",
    "synthetic_stay": "True on the STAY appended to a demonstration that ended at the goal or "
    "by the participant (the learner observes it; people cannot press STAY).",
    "participant": "The participant (participant_id of participants.csv).",
    "worker": "The participant's MTurk or Prolific id, pseudonymised as in participants.csv "
    "(w_ + salted hash; empty for lab participants).",
    "session": "The learning session: session_id of sessions.csv, or of tutorial_sessions.csv "
    "for a tutorial's (tutorial_session_id in episodes.csv and events.csv).",
    "episode": "The episode (episode_id of episodes.csv).",
    "learner": "The session's learner (bam, model-based, global-cost, cloning).",
    "learner_update": "Agent episodes: the learner update whose greedy policy acted "
    "(update_index of evaluations.csv); -1 for demonstrations.",
}


@dataclass(frozen=True)
class StudyFile:
    """The study configuration the export names in its metadata."""

    name: str
    sha256: str

    @classmethod
    def read(cls, path: Path) -> StudyFile:
        try:
            content = path.read_bytes()
        except OSError as error:
            raise DatasetError(f"cannot read the study file {path}: {error}") from None
        return cls(path.name, hashlib.sha256(content).hexdigest())


def study_datasets(
    db: Database,
    study: StudyFile,
    pseudonymize: bool = True,
    secret: str | None = None,
    include_excluded: bool = False,
    exported_at: datetime | None = None,
) -> list[Dataset]:
    """One dataset per environment with the study's ended episodes (see the module
    docstring); raises ``DatasetError`` when there is none."""
    if pseudonymize and secret is None:
        secret = database_secret(db)
    with db.read() as s:
        participants = {p.id: p for p in s.scalars(select(Participant))}
        sessions = s.scalars(select(LearningSession).order_by(LearningSession.id)).all()
        episodes = s.scalars(select(Episode).order_by(Episode.session_id, Episode.index)).all()
        done = s.execute(
            select(LearnerUpdate.session_id, LearnerUpdate.update_index).where(
                LearnerUpdate.status == UpdateStatus.DONE
            )
        ).all()
        events = s.execute(
            select(
                Event.session_id,
                Event.record,
                Event.state,
                Event.action,
                Event.next_state,
                Event.feedback,
                Event.episode_index,
                Event.stay_state,
            )
            .where(Event.session_id.is_not(None))
            .order_by(Event.id)
        ).all()
    kept = {
        x.id: x
        for x in sessions
        if include_excluded or participants[x.participant_id].excluded_at is None
    }
    left_out = sum(1 for p in participants.values() if p.excluded_at is not None)
    steps = _steps_by_episode(e for e in events if e.session_id in kept)
    updates: dict[int, list[int]] = {}
    for session_id, index in done:
        updates.setdefault(session_id, []).append(index)

    by_environment: dict[str, list[DatasetEpisode]] = {}
    counts: dict[str, dict[str, Any]] = {}
    for episode in episodes:
        session = kept.get(episode.session_id)
        if session is None or episode.ended_at is None:
            continue
        taken = steps.get((episode.session_id, episode.index), [])
        if not taken:
            continue
        participant = participants[session.participant_id]
        worker = participant.platform_participant_id
        if pseudonymize:
            assert secret is not None
            worker, _ = participant_pseudonyms(participant, secret)
        acting = -1
        if episode.kind == EpisodeKind.AGENT:
            # The agent acts on its latest done update; all of those up to the episode's
            # index were done before its first step, and none after it could be.
            acting = max((i for i in updates.get(session.id, []) if i <= episode.index), default=-1)
        by_environment.setdefault(session.environment, []).append(
            _dataset_episode(episode, session, taken, worker or "", acting)
        )
        count = counts.setdefault(
            session.environment,
            {"participants": set(), EpisodeKind.DEMONSTRATION: 0, EpisodeKind.AGENT: 0},
        )
        count["participants"].add(session.participant_id)
        count[episode.kind] += 1
    if not by_environment:
        raise DatasetError(
            "the database holds no ended episode to export"
            + (
                f" ({left_out} excluded participant(s) left out: --include-excluded)"
                if left_out and not include_excluded
                else ""
            )
        )
    when = (exported_at or datetime.now(UTC)).isoformat()
    return [
        _dataset(
            environment, found, counts[environment], study, when, include_excluded, pseudonymize
        )
        for environment, found in sorted(by_environment.items())
    ]


def _dataset(
    environment: str,
    found: list[DatasetEpisode],
    count: dict[str, Any],
    study: StudyFile,
    when: str,
    include_excluded: bool,
    pseudonymize: bool,
) -> Dataset:
    """The dataset of one environment's episodes, ``count`` its participants and episodes of
    each kind."""
    return Dataset(
        environment=environment,
        name=DATASET_NAME,
        episodes=found,
        description=(
            f"BAM Study: the participants' episodes in {environment}: demonstrations and "
            "the agents' tries, with the participants' feedback on the agents' steps."
        ),
        algorithm="human teaching (demonstrations, and feedback on the agent's tries)",
        metadata={
            "study_file": study.name,
            "study_sha256": study.sha256,
            "exported_at": when,
            "participants": len(count["participants"]),
            "episodes": len(found),
            "demonstrations": count[EpisodeKind.DEMONSTRATION],
            "agent_episodes": count[EpisodeKind.AGENT],
            "excluded_participants": "included" if include_excluded else "left out",
            "pseudonymised": pseudonymize,
            "infos": INFOS,
        },
    )


Step = dict[str, Any]


def _steps_by_episode(events: Iterable[Any]) -> dict[tuple[int, int], list[Step]]:
    """The steps of every episode, from the events in order: demonstrated moves and agent
    steps, the synthetic STAY of a demonstration's end, and feedback on the latest agent step
    (as ``updates.records_of`` hands them to the learner)."""
    steps: dict[tuple[int, int], list[Step]] = {}
    latest_agent_step: dict[int, Step] = {}
    for event in events:
        if event.record in (Observed.DEMONSTRATION, Observed.AGENT_STEP):
            step = {
                "state": event.state,
                "action": event.action,
                "next_state": event.next_state,
                "feedback": 0,
                "synthetic_stay": False,
            }
            steps.setdefault((event.session_id, event.episode_index), []).append(step)
            if event.record == Observed.AGENT_STEP:
                latest_agent_step[event.session_id] = step
        elif event.record == Observed.FEEDBACK:
            latest = latest_agent_step.get(event.session_id)
            if latest is None:
                raise DatasetError(
                    f"session {event.session_id}: feedback with no agent step before it"
                )
            latest["feedback"] = event.feedback
        if event.stay_state is not None:
            steps.setdefault((event.session_id, event.episode_index), []).append(
                {
                    "state": event.next_state,
                    "action": STAY,
                    "next_state": event.stay_state,
                    "feedback": 0,
                    "synthetic_stay": True,
                }
            )
    return steps


def _dataset_episode(
    episode: Episode, session: LearningSession, taken: list[Step], worker: str, acting: int
) -> DatasetEpisode:
    # The first step's state: databases written before the fix of teaching.move hold, for a
    # demonstration, the state after its first move as the episode's start_state.
    states = [int(taken[0]["state"])]
    for step in taken:
        if step["state"] != states[-1]:
            raise DatasetError(
                f"episode {episode.id}: a step from state {step['state']} follows state "
                f"{states[-1]}: the events are inconsistent"
            )
        states.append(int(step["next_state"]))
    length = len(taken) + 1
    return DatasetEpisode(
        task=int(episode.task),
        states=states,
        actions=[int(step["action"]) for step in taken],
        infos={
            "kind": [episode.kind] * length,
            "feedback": [0] + [int(step["feedback"]) for step in taken],
            "synthetic_stay": [False] + [bool(step["synthetic_stay"]) for step in taken],
            "participant": [int(session.participant_id)] * length,
            "worker": [worker] * length,
            "session": [int(session.id)] * length,
            "episode": [int(episode.id)] * length,
            "learner": [session.learner] * length,
            "learner_update": [-1]
            + [acting if episode.kind == EpisodeKind.AGENT else -1] * len(taken),
        },
    )
