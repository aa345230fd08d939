"""The string vocabularies of the study's tables, each once: the values a column stores, the
API returns and the export writes.

Each is a ``StrEnum``: a member is the string it stands for (``ParticipantStatus.RETURNED ==
"returned"``), so the stored values are the strings listed here and a row read back compares
equal to its member. A value added here is a value the database may hold: the export's and the
analysis's lists are derived from these, and ``tests/app/storage/test_vocabulary.py`` holds the
stored strings, so that a change to one is a change seen in review.
"""

from __future__ import annotations

from enum import StrEnum, unique


class Vocabulary(StrEnum):
    """A vocabulary's member: its string, which its ``repr`` shows too (so that Pydantic's
    message for a value outside a literal of members lists the strings, as for a literal of
    strings)."""

    def __repr__(self) -> str:
        return repr(self.value)


@unique
class ParticipantStatus(Vocabulary):
    """Where a participant is in the study's flow (``participants.status``), one at a time."""

    # In the order a participant can reach them (the export's columns follow it).
    WAITING = "waiting"  # arrived while the study was full, for a place (``places``)
    ARRIVED = "arrived"  # has the consent page (after the device check, in a study with one)
    INCOMPATIBLE = "incompatible"  # turned away by the device check before consent: flow ends
    CONSENTED = "consented"  # domain and learning sessions assigned
    DECLINED = "declined"  # did not consent: the flow ends
    TUTORIAL = "tutorial"  # teaching the tutorial's agent
    TEACHING = "teaching"  # teaching the study's agents
    QUESTIONNAIRE = "questionnaire"  # answering the post-study questionnaire (a study with one)
    COMPLETED = "completed"  # finished; the completion code issued
    SUBMITTED = "submitted"  # the platform confirmed the submission (MTurk's form posted)
    RETURNED = "returned"  # returned the task on the platform: the flow ends
    ABANDONED = "abandoned"  # idle too long (``BAM_ABANDON_MINUTES``); may come back


# The statuses of the flow, in order (the ones a participant who comes back returns to).
FLOW_STATUSES = (
    ParticipantStatus.ARRIVED,
    ParticipantStatus.CONSENTED,
    ParticipantStatus.TUTORIAL,
    ParticipantStatus.TEACHING,
    ParticipantStatus.QUESTIONNAIRE,
    ParticipantStatus.COMPLETED,
    ParticipantStatus.SUBMITTED,
)
# In the flow and not yet finished: the participants who hold a place.
IN_PROGRESS = FLOW_STATUSES[:5]
# Finished the study: completed, and submitted where the platform confirms it.
FINISHED_STATUSES = (ParticipantStatus.COMPLETED, ParticipantStatus.SUBMITTED)


@unique
class ExclusionMark(Vocabulary):
    """The experimenter's marks that ``status_changes.status`` records beside the statuses
    (exclusion leaves the status as it is: ``participants.excluded_at``)."""

    EXCLUDED = "excluded"
    INCLUDED = "included"  # an exclusion undone


@unique
class SessionKind(Vocabulary):
    """What a learning session is for (``learning_sessions.kind``)."""

    TUTORIAL = "tutorial"  # the tutorial's agent, before the study's (a study file with one)
    STUDY = "study"  # one of the study's agents, counted in the export


@unique
class SessionStatus(Vocabulary):
    """Where a learning session is (``learning_sessions.status``)."""

    PENDING = "pending"  # not reached yet
    ACTIVE = "active"  # being taught (at most one per participant)
    FINISHED = "finished"  # taught and left


@unique
class Mode(Vocabulary):
    """What the participant's arrow keys and the agent do (``learning_sessions.mode``,
    ``events.mode``)."""

    IDLE = "idle"  # the arrows move the agent; the learner sees the move alone
    DEMONSTRATE = "demonstrate"  # the arrows demonstrate actions
    AGENT = "agent"  # the agent acts on its learner's policy; the participant gives feedback


@unique
class LastAction(Vocabulary):
    """Who moved the agent last (``learning_sessions.last_action``); feedback needs ``AGENT``."""

    DEMONSTRATION = "demonstration"
    AGENT = "agent"
    IDLE = "idle"


@unique
class EpisodeKind(Vocabulary):
    """Who acts in an episode (``episodes.kind``)."""

    DEMONSTRATION = "demonstration"  # the participant
    AGENT = "agent"  # the agent, on its learner's policy


@unique
class EpisodeEnd(Vocabulary):
    """Why an episode ended (``episodes.end_reason``, ``events.episode_end``)."""

    END = "end"  # the participant ended it (Stop)
    GOAL = "goal"  # the task's goal was reached
    HORIZON = "horizon"  # an agent episode took the environment's horizon of actions
    TASK = "task"  # another task was selected
    MODE = "mode"  # the mode was changed
    RESET = "reset"  # the agent was put at a new start
    FINISH = "finish"  # the agent was finished


@unique
class Observed(Vocabulary):
    """What the learner observes from an event (``events.record``; None: nothing)."""

    DEMONSTRATION = "demonstration"  # a demonstrated step
    AGENT_STEP = "agent_step"  # a step of the agent (its feedback 0 until some is given)
    IDLE_MOVE = "transition"  # a move in idle mode: a transition alone, no action's intent
    FEEDBACK = "feedback"  # +1 or -1 on the latest agent step


@unique
class UpdateStatus(Vocabulary):
    """Where a learner update is (``learner_updates.status``)."""

    PENDING = "pending"  # queued or running
    DONE = "done"  # learnt and evaluated
    FAILED = "failed"  # gave up after its attempts (``error`` says why)


@unique
class CheckStatus(Vocabulary):
    """Where an attention check is (``attention_checks.status``)."""

    PENDING = "pending"  # not reached yet
    ACTIVE = "active"  # being taken
    PASSED = "passed"  # the star reached within the moves allowed
    FAILED = "failed"  # the moves ran out


@unique
class ReviewDecision(Vocabulary):
    """The experimenter's decision on a submission (``reviews.decision``)."""

    APPROVED = "approved"
    REJECTED = "rejected"


@unique
class ReviewState(Vocabulary):
    """Whether the platform has taken a review's decision (``reviews.state``)."""

    PENDING = "pending"  # recorded before the platform is called
    DONE = "done"  # the platform took it


@unique
class BonusState(Vocabulary):
    """Where a bonus's payment is (``bonuses.state``; ``platforms/review/``)."""

    PENDING = "pending"  # recorded before the platform is called
    IN_DOUBT = "in_doubt"  # pending past the platform's memory of its token: paid or not unknown
    SET_UP = "set_up"  # Prolific: the bonus set up (``setup_id``), not yet paid
    PAYING = "paying"  # Prolific: the one pay call is being made
    PAID = "paid"  # the platform took it


@unique
class ErasedBy(Vocabulary):
    """Who asked for a participant's erasure (``erasures.erased_by``)."""

    PARTICIPANT = "participant"
    EXPERIMENTER = "experimenter"


@unique
class ReplicaAssignmentStatus(Vocabulary):
    """Where a worker's turn at an assignment is in the local MTurk replica
    (``mturk_replica_assignments.status``): MTurk's AssignmentStatus, and its HIT's return."""

    ACCEPTED = "accepted"  # the worker holds it
    RETURNED = "returned"  # given back; the assignment goes to the next worker who accepts
    SUBMITTED = "submitted"  # the study's form posted
    APPROVED = ReviewDecision.APPROVED.value
    REJECTED = ReviewDecision.REJECTED.value
