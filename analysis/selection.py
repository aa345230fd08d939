"""Which learning sessions and episodes the analysis counts: the sessions of the participants
who completed the study (``include_unfinished`` adds the taught sessions of the others), with a
note of what was left out and why; and the empty episodes taken out of the counts (see
``analysis.data``)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd

from analysis import cells
from analysis.columns import EPISODE_COLUMNS, EPISODES_FILE
from analysis.options import InputError
from server.app.storage.vocabulary import (
    FINISHED_STATUSES,
    EpisodeEnd,
    EpisodeKind,
    ExclusionMark,
    ParticipantStatus,
)

# Participant statuses of those who completed the study (the server's flow statuses).
COMPLETED_STATUSES = FINISHED_STATUSES


# Every other status the server gives a participant, as the notes name it: why the participant
# did not finish. A status missing here is named as it is ("status 'x'"); a new status of the
# server gets its entry here (tests/analysis/test_sessions.py checks that each has one).
UNFINISHED_REASONS: dict[str, str] = {
    ParticipantStatus.RETURNED: "returned the task",
    ParticipantStatus.ABANDONED: "timed out",
    ParticipantStatus.DECLINED: "declined consent",
    ParticipantStatus.INCOMPATIBLE: "turned away by the device check",
    ParticipantStatus.ARRIVED: "still in the study",
    ParticipantStatus.CONSENTED: "still in the study",
    ParticipantStatus.TUTORIAL: "still in the study",
    ParticipantStatus.TEACHING: "still in the study",
    ParticipantStatus.QUESTIONNAIRE: "still in the study",
    ParticipantStatus.WAITING: "waiting for a place (never started)",
}


NOT_LISTED = "not in {source}"

# A decision on a participant's submitted work (reviews.csv's ``decision``) that judged it invalid,
# and Prolific's status of a submission rejected there (participants.csv's ``prolific_status``).
REJECTED_DECISION = "rejected"
REJECTED_PROLIFIC_STATUS = "REJECTED"


def keep_finished(
    sessions: pd.DataFrame,
    evaluations: pd.DataFrame,
    participants: pd.DataFrame | None,
    source: str,
    *,
    include_unfinished: bool,
    notes: list[str],
    unreadable: str | None = None,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The learning sessions Table 1 counts, and their evaluations: those of the participants
    who completed the study (``COMPLETED_STATUSES``) and, with ``include_unfinished``, the
    taught ones (at least one episode or action) of the others. A note says how many were left out
    (or added), by why their participants did not finish (``UNFINISHED_REASONS``)."""
    if participants is None or not {"participant_id", "status"} <= set(participants.columns):
        if unreadable is not None:
            why = unreadable
        elif participants is None:
            why = f"no {source} given"
        else:
            why = f"{source} has no columns 'participant_id' and 'status'"
        notes.append(
            f"participant statuses not checked ({why}): every learning session is counted, "
            "whether or not its participant completed the study"
        )
        return sessions, evaluations
    statuses = dict(
        zip(
            participants["participant_id"].astype(str).str.strip(),
            participants["status"].astype(str).str.strip().str.lower(),
            strict=True,
        )
    )
    status = sessions["participant_id"].map(statuses)
    unfinished = ~status.isin(COMPLETED_STATUSES)
    if not unfinished.any():
        return sessions, evaluations
    reason = status.map(lambda s: _unfinished_reason(s, source))
    taught = sessions["session_id"].isin(taught_sessions(evaluations))
    left_out = unfinished & ~taught if include_unfinished else unfinished
    people = int(sessions.loc[unfinished, "participant_id"].nunique())
    if include_unfinished:
        added = unfinished & taught
        if added.any():
            notes.append(
                f"--include-unfinished: counted {count_phrase(int(added.sum()), 'taught learning session')}"
                f" of {count_phrase(int(sessions.loc[added, 'participant_id'].nunique()), 'participant')}"
                f" who did not complete the study ({_by_reason(reason[added])})"
            )
        if left_out.any():
            notes.append(
                f"left out {count_phrase(int(left_out.sum()), 'learning session')} never taught (no episode "
                "or action) of participants who did not complete the study "
                f"({_by_reason(reason[left_out])})"
            )
    else:
        untaught = int((unfinished & ~taught).sum())
        never = (
            "none was taught"
            if untaught == int(unfinished.sum())
            else f"{untaught} never taught (no episode or action)"
            if untaught
            else "all were taught"
        )
        addable = int((unfinished & taught).sum())
        notes.append(
            f"left out {count_phrase(int(unfinished.sum()), 'learning session')} of "
            f"{count_phrase(people, 'participant')} who did not complete the study "
            f"({_by_reason(reason[unfinished])}); {never}"
            + (f"; --include-unfinished adds the {addable} taught" if addable else "")
        )
    keep = ~left_out
    sessions = sessions.loc[keep].reset_index(drop=True)
    evaluations = evaluations.loc[
        evaluations["session_id"].isin(set(sessions["session_id"]))
    ].reset_index(drop=True)
    return sessions, evaluations


def taught_sessions(evaluations: pd.DataFrame) -> set[object]:
    """The sessions taught something: an evaluation after at least one episode or one action.
    An evaluation alone is not teaching: the agent is evaluated before any data
    (``update_index`` 0, no episode and no action), so an agent the participant never opened
    has one too."""
    done = evaluations["episodes"].fillna(0).gt(0) | evaluations["actions"].fillna(0).gt(0)
    return set(evaluations.loc[done, "session_id"])


def _unfinished_reason(status: object, source: str) -> str:
    if not isinstance(status, str):  # the participant is not in the participants table
        return NOT_LISTED.format(source=source)
    return UNFINISHED_REASONS.get(status, f"status {status!r}")


def _by_reason(reasons: pd.Series) -> str:
    """``"returned the task: 6, timed out: 2"``: sessions per reason, most first."""
    counts = reasons.value_counts(sort=False)
    ordered = sorted(counts.items(), key=lambda item: (-item[1], item[0]))
    return ", ".join(f"{reason}: {count}" for reason, count in ordered)


def count_phrase(number: int, noun: str) -> str:
    return f"{number} {noun}{'' if number == 1 else 's'}"


def empty_episodes(episodes: pd.DataFrame, source: str = EPISODES_FILE) -> pd.Series:
    """Which episodes are empty (module docstring): agent episodes of one action that ended
    at the goal where they began."""
    cells.require_columns(episodes, EPISODE_COLUMNS, source)
    start, start_missing = cells.raw(episodes, "start_state")
    end, _ = cells.raw(episodes, "end_state")
    kind, _ = cells.raw(episodes, "kind")
    reason, _ = cells.raw(episodes, "end_reason")
    actions, _ = cells.raw(episodes, "actions")
    return (
        (kind == EpisodeKind.AGENT)
        & (reason == EpisodeEnd.GOAL)
        & (actions == "1")
        & ~start_missing
        & (start == end)
    )


def discount_empty_episodes(
    evaluations: pd.DataFrame, episodes: pd.DataFrame, source: str, notes: list[str]
) -> pd.DataFrame:
    """The evaluations with empty episodes taken out of their cumulative counts: an empty
    episode ended by update u takes one episode and its action from every evaluation of its
    session from update u on. Episodes of sessions that have no evaluations here (tutorials,
    sessions left out) are ignored."""
    empty = empty_episodes(episodes, source)
    session_ids, _ = cells.raw(episodes, "session_id")
    empty &= session_ids.isin(set(evaluations["session_id"]))
    if not empty.any():
        return evaluations
    text, _ = cells.raw(episodes, "update_index")
    numbers = pd.to_numeric(text, errors="coerce")
    bad = empty & ~((numbers >= 0) & (numbers == np.round(numbers)))
    cells.first_bad(
        episodes,
        "update_index",
        source,
        bad,
        lambda value: f"{value!r} is not the update of an ended episode (a whole number >= 0)",
    )
    updates = numbers[empty].astype(np.int64)
    out = evaluations.copy()
    for session_id, update in zip(session_ids[empty], updates, strict=True):
        later = (out["session_id"] == session_id) & (out["update_index"] >= update)
        out.loc[later, "episodes"] -= 1
        out.loc[later, "actions"] -= 1
    count = int(empty.sum())
    sessions = int(session_ids[empty].nunique())
    notes.append(
        f"{count_phrase(count, 'empty episode')} in {count_phrase(sessions, 'learning session')} not "
        "counted (an agent's try from the goal that ended there at once: one action, "
        "start_state = end_state, end_reason goal; the server no longer records these)"
    )
    return out


def excluded_participants(
    participants: pd.DataFrame | None, source: str, required: bool
) -> set[str] | None:
    """Ids of participants marked excluded (an ``excluded`` column that is true, as the study
    server exports it, or a ``status`` of ``excluded``); None when that is unknown (an error
    instead when ``required``)."""
    if participants is None:
        if required:
            raise InputError(f"--exclude-excluded needs {source}, which was not given")
        return None
    markers = [c for c in ("excluded", "status") if c in participants.columns]
    if "participant_id" not in participants.columns or not markers:
        if required:
            needed = "'participant_id' and 'excluded' (or 'status')"
            raise InputError(
                f"{source}: --exclude-excluded needs the columns {needed}, which the file "
                f"does not have (found: {', '.join(repr(str(c)) for c in participants.columns)})"
            )
        return None
    marked = pd.Series(False, index=participants.index)
    if "excluded" in participants.columns:
        marked |= (
            participants["excluded"].astype(str).str.strip().str.lower().isin(cells.TRUE_WORDS)
        )
    if "status" in participants.columns:
        marked |= (
            participants["status"].astype(str).str.strip().str.lower() == ExclusionMark.EXCLUDED
        )
    return set(participants.loc[marked, "participant_id"].astype(str).str.strip())


def flagged_participants(quality: pd.DataFrame, flags: Sequence[str], source: str) -> set[str]:
    """Ids of the participants ``quality`` (``quality.csv``) flags with any of ``flags``."""
    missing = [c for c in ("participant_id", "flags") if c not in quality.columns]
    if missing:
        raise InputError(
            f"{source}: --exclude-flagged needs the columns 'participant_id' and 'flags', which "
            f"the file does not have (found: {', '.join(repr(str(c)) for c in quality.columns)})"
        )
    wanted = set(flags)
    words = quality["flags"].fillna("").astype(str).str.split()
    marked = words.map(lambda found: bool(wanted & set(found)))
    return set(quality.loc[marked, "participant_id"].astype(str).str.strip())


def drop_flagged(
    sessions: pd.DataFrame,
    evaluations: pd.DataFrame,
    flagged: set[str],
    flags: Sequence[str],
    source: str,
    notes: list[str],
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The learning sessions and evaluations without those of the ``flagged`` participants,
    with a note that says how many were left out and why."""
    dropped = sessions["participant_id"].astype(str).str.strip().isin(flagged)
    people = int(sessions.loc[dropped, "participant_id"].nunique())
    notes.append(
        f"excluded {count_phrase(int(dropped.sum()), 'learning session')} of "
        f"{count_phrase(people, 'participant')} flagged {' or '.join(flags)} in {source}"
    )
    kept = sessions.loc[~dropped].reset_index(drop=True)
    if kept.empty:
        raise InputError(
            f"no learning sessions are left after excluding the participants flagged "
            f"{' or '.join(flags)} in {source}"
        )
    evaluations = evaluations.loc[evaluations["session_id"].isin(kept["session_id"])]
    return kept, evaluations.reset_index(drop=True)


def rejected_participants(
    reviews: pd.DataFrame | None,
    participants: pd.DataFrame | None,
    reviews_source: str,
) -> set[str]:
    """Ids of the participants whose submitted work was rejected: a ``decision`` of
    ``rejected`` in ``reviews`` (``reviews.csv``; one still ``pending`` too, since the decision
    is the experimenter's and final, only the platform's confirmation is outstanding), or a
    ``prolific_status`` of ``REJECTED`` in ``participants`` (a rejection made on Prolific's
    site)."""
    rejected: set[str] = set()
    if reviews is not None:
        missing = [c for c in ("participant_id", "decision") if c not in reviews.columns]
        if missing:
            raise InputError(
                f"{reviews_source}: rejections are read from the columns 'participant_id' and "
                "'decision', which the file does not have (found: "
                f"{', '.join(repr(str(c)) for c in reviews.columns)})"
            )
        decided = reviews["decision"].astype(str).str.strip().str.lower() == REJECTED_DECISION
        rejected |= set(reviews.loc[decided, "participant_id"].astype(str).str.strip())
    if participants is not None and {"participant_id", "prolific_status"} <= set(
        participants.columns
    ):
        on_prolific = (
            participants["prolific_status"].astype(str).str.strip().str.upper()
            == REJECTED_PROLIFIC_STATUS
        )
        rejected |= set(participants.loc[on_prolific, "participant_id"].astype(str).str.strip())
    return rejected


def apply_rejections(
    sessions: pd.DataFrame,
    evaluations: pd.DataFrame,
    rejected: set[str],
    *,
    include_rejected: bool,
    reviews_source: str,
    notes: list[str],
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The learning sessions and evaluations without those of the ``rejected`` participants
    (with ``include_rejected``, with them), and a note of how many, when there are any."""
    of_rejected = sessions["participant_id"].astype(str).str.strip().isin(rejected)
    if not of_rejected.any():
        return sessions, evaluations
    counted = (
        f"{count_phrase(int(of_rejected.sum()), 'learning session')} of "
        f"{count_phrase(int(sessions.loc[of_rejected, 'participant_id'].nunique()), 'participant')}"
        f" whose submission was rejected ({reviews_source} or Prolific)"
    )
    if include_rejected:
        notes.append(f"--include-rejected: counted {counted}")
        return sessions, evaluations
    notes.append(f"left out {counted}; --include-rejected counts them")
    kept = sessions.loc[~of_rejected].reset_index(drop=True)
    if kept.empty:
        raise InputError(
            "no learning sessions are left after leaving out the participants whose submission "
            "was rejected; --include-rejected counts them"
        )
    evaluations = evaluations.loc[evaluations["session_id"].isin(kept["session_id"])]
    return kept, evaluations.reset_index(drop=True)
