"""The participant flow, CONSORT style: how many participants arrived, consented, completed and
were analysed, and at each step how many left and why, counted from the export's statuses.

Every participant who arrived ends in exactly one box: a way of leaving (a final ``status`` in
``participants.csv``, a withdrawal in ``erasures.csv``, or one of the analysis's exclusions of
a participant who completed) or *analysed*. So each stage is the one before it less the boxes
that leave it, and *arrived* is the sum of all the boxes that leave plus *analysed* (less those
``--include-unfinished`` adds back). The analysed box is counted from the learning sessions
Table 1 counts, not from the statuses, so that the arithmetic checks the selection.

Consent is read from ``consented_at`` (the first time the status became ``consented``) or, where
that column is missing, from the participant's learning sessions, which the server creates at
consent; a withdrawal (``erasures.csv``) left from after consent when it erased learning
sessions (``learning_sessions_rows``). The analysis's exclusions of participants who completed
are taken in the order the analysis applies them: the experimenter's exclusion
(``--exclude-excluded``), a rejected submission (unless ``--include-rejected``), then each
quality check of ``--exclude-flagged`` in turn; a participant is counted once, under the first
that applies.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import pandas as pd

from analysis import cells
from analysis.columns import ERASURES_FILE, PARTICIPANTS_FILE, QUALITY_FILE, REVIEWS_FILE
from analysis.selection import (
    COMPLETED_STATUSES,
    excluded_participants,
    rejected_participants,
)

ARRIVED, CONSENTED, COMPLETED, ANALYSED = "arrived", "consented", "completed", "analysed"
STAGES = (ARRIVED, CONSENTED, COMPLETED, ANALYSED)
STAGE_LABELS = {
    ARRIVED: "Arrived",
    CONSENTED: "Consented",
    COMPLETED: "Completed the study",
    ANALYSED: "Analysed (Table 1)",
}
# Statuses of a participant still in the study after consent (the server's flow statuses).
IN_STUDY = ("consented", "tutorial", "teaching", "questionnaire")
# The statuses a participant can end in before consent, and after it (the server's
# ``storage.vocabulary.ParticipantStatus``); "returned" and "abandoned" can be either.
BEFORE_CONSENT = ("waiting", "incompatible", "declined", "arrived", "returned", "abandoned")
AFTER_CONSENT = ("returned", "abandoned", *IN_STUDY, *COMPLETED_STATUSES)

# The columns of participant_flow.csv.
FLOW_COLUMNS = ("stage", "kind", "box", "label", "participants", "learning_sessions", "definition")
# kind: "stage" (everyone who got that far), "left" (left after the stage: the stage below is
# this one less every "left" box), "added" (counted in the stage below, though not in this one)
# and "counted" (still in: for information, not subtracted).


@dataclass(frozen=True)
class FlowBox:
    """One box of the flow: a stage, or the participants who left it (or were added) one way."""

    stage: str  # the stage it belongs to or leaves from
    kind: str  # stage, left, added or counted (FLOW_COLUMNS)
    box: str  # a short name: arrived, declined, rejected, flagged_long_idle, ...
    label: str  # what a reader sees
    participants: int
    learning_sessions: int  # their learning sessions in the export (or, analysed: counted)
    definition: str  # where the number comes from


@dataclass(frozen=True)
class ParticipantFlow:
    boxes: tuple[FlowBox, ...]
    remarks: tuple[str, ...]  # what the flow could not count, and why

    def frame(self) -> pd.DataFrame:
        rows = [{column: getattr(box, column) for column in FLOW_COLUMNS} for box in self.boxes]
        return pd.DataFrame(rows, columns=list(FLOW_COLUMNS))

    def stage(self, name: str) -> FlowBox:
        return next(b for b in self.boxes if b.kind == "stage" and b.stage == name)

    def leaving(self, name: str) -> list[FlowBox]:
        return [b for b in self.boxes if b.stage == name and b.kind in ("left", "added")]

    def counted(self, name: str) -> list[FlowBox]:
        return [b for b in self.boxes if b.stage == name and b.kind == "counted"]


def participant_flow(
    tables: Mapping[str, pd.DataFrame | None],
    counted_sessions: pd.DataFrame,
    *,
    exclude_excluded: bool = False,
    include_rejected: bool = False,
    exclude_flagged: Sequence[str] = (),
    include_unfinished: bool = False,
) -> ParticipantFlow | None:
    """The flow of the export's ``tables`` (``analysis.data.load_tables``' ``tables``), with
    ``counted_sessions`` the learning sessions Table 1 counts under these options; None when
    there is no ``participants.csv`` with a ``status`` to count from.

    Long on purpose: each box of the flow diagram is one ``add`` (its stage, label and rule
    side by side), in the diagram's order, so the function reads as the diagram does."""
    participants = tables.get("participants")
    if participants is None or not {"participant_id", "status"} <= set(participants.columns):
        return None
    from server.app.export.quality import FLAGS

    remarks: list[str] = []
    people = pd.DataFrame(
        {
            "participant_id": participants["participant_id"].astype(str).str.strip(),
            "status": participants["status"].astype(str).str.strip().str.lower(),
        }
    )
    sessions = tables.get("sessions")
    owners = (
        sessions["participant_id"].astype(str).str.strip()
        if sessions is not None
        else pd.Series(dtype=str)
    )
    per_person = owners.value_counts()
    people["sessions"] = people["participant_id"].map(per_person).fillna(0).astype(int)
    # Only a participant who consented can be in these statuses.
    consented = (people["sessions"] > 0) | people["status"].isin(AFTER_CONSENT[2:])
    if "consented_at" in participants.columns:
        consented |= ~cells.optional_text(participants["consented_at"]).eq("").to_numpy()
    people["consented"] = consented.to_numpy()

    counted_ids = counted_sessions["participant_id"].astype(str).str.strip()
    boxes: list[FlowBox] = []

    def add(stage: str, kind: str, box: str, label: str, chosen: pd.Series, why: str) -> None:
        if kind == "counted":  # their sessions Table 1 counts (with --include-unfinished, taught)
            sessions = int(counted_ids.isin(set(people.loc[chosen, "participant_id"])).sum())
        else:
            sessions = int(people.loc[chosen, "sessions"].sum())
        boxes.append(FlowBox(stage, kind, box, label, int(chosen.sum()), sessions, why))

    erasures = _erasures(tables.get("erasures"), remarks)
    arrived = len(people) + len(erasures)
    boxes.append(
        FlowBox(
            ARRIVED,
            "stage",
            ARRIVED,
            STAGE_LABELS[ARRIVED],
            arrived,
            int(people["sessions"].sum() + erasures["sessions"].sum()),
            f"rows of {PARTICIPANTS_FILE} (arrivals that were not previews) and of "
            f"{ERASURES_FILE} (participants whose data was erased)",
        )
    )
    status = people["status"]
    before = ~people["consented"]
    add(
        ARRIVED,
        "left",
        "waiting",
        "Waited for a place, never started",
        status.eq("waiting") & before,
        "status waiting",
    )
    add(
        ARRIVED,
        "left",
        "incompatible",
        "Turned away by the device check",
        status.eq("incompatible") & before,
        "status incompatible",
    )
    add(
        ARRIVED,
        "left",
        "declined",
        "Declined consent",
        status.eq("declined") & before,
        "status declined",
    )
    add(
        ARRIVED,
        "left",
        "at_consent",
        "Still at the consent page",
        status.eq("arrived") & before,
        "status arrived",
    )
    add(
        ARRIVED,
        "left",
        "returned_before_consent",
        "Returned the task before consenting",
        status.eq("returned") & before,
        "status returned, never consented",
    )
    add(
        ARRIVED,
        "left",
        "timed_out_before_consent",
        "Timed out before consenting",
        status.eq("abandoned") & before,
        "status abandoned (idle too long), never consented",
    )
    early, late = ~erasures["after_consent"], erasures["after_consent"]
    boxes.append(
        FlowBox(
            ARRIVED,
            "left",
            "withdrew_before_consent",
            "Withdrew before consenting (data erased)",
            int(early.sum()),
            0,
            f"rows of {ERASURES_FILE} that erased no learning session",
        )
    )
    # Any other status (one the analysis does not know, or one that cannot follow consent found
    # after it) has a box of its own, so that everybody is in exactly one box.
    other = ~status.isin(BEFORE_CONSENT)
    for name in sorted(set(status[other & before])):
        add(
            ARRIVED,
            "left",
            f"status_{name}_before_consent",
            f"Status {name!r}, never consented",
            status.eq(name) & before,
            f"status {name!r} (not one the analysis knows)",
        )

    after = people["consented"]
    other = ~status.isin(AFTER_CONSENT)
    add(
        CONSENTED,
        "stage",
        CONSENTED,
        STAGE_LABELS[CONSENTED],
        after,
        "consented_at set, or learning sessions assigned (the server assigns them at consent)",
    )
    boxes[-1] = replace(
        boxes[-1],
        participants=boxes[-1].participants + int(late.sum()),
        learning_sessions=boxes[-1].learning_sessions + int(erasures["sessions"].sum()),
    )
    boxes.append(
        FlowBox(
            CONSENTED,
            "left",
            "withdrew",
            "Withdrew (data erased)",
            int(late.sum()),
            int(erasures["sessions"].sum()),
            f"rows of {ERASURES_FILE} that erased learning sessions (erased_by participant: "
            f"{int((late & (erasures['by'] == 'participant')).sum())}, experimenter on request: "
            f"{int((late & (erasures['by'] == 'experimenter')).sum())})",
        )
    )
    add(
        CONSENTED,
        "left",
        "returned",
        "Returned the task",
        status.eq("returned") & after,
        "status returned (MTurk HIT returned; Prolific RETURNED or TIMED-OUT)",
    )
    add(
        CONSENTED,
        "left",
        "timed_out",
        "Timed out",
        status.eq("abandoned") & after,
        "status abandoned (idle too long)",
    )
    add(
        CONSENTED,
        "left",
        "in_study",
        "Still in the study",
        status.isin(IN_STUDY) & after,
        f"status {', '.join(IN_STUDY)}",
    )
    for name in sorted(set(status[other & after])):
        add(
            CONSENTED,
            "left",
            f"status_{name}",
            f"Status {name!r}",
            status.eq(name) & after,
            f"status {name!r} (not one the analysis knows)",
        )

    completed = status.isin(COMPLETED_STATUSES)
    add(
        COMPLETED,
        "stage",
        COMPLETED,
        STAGE_LABELS[COMPLETED],
        completed,
        f"status {' or '.join(COMPLETED_STATUSES)}",
    )
    ids = people["participant_id"]
    remaining = completed.copy()
    excluded = excluded_participants(participants, PARTICIPANTS_FILE, False) or set()
    marked = ids.isin(excluded)
    if exclude_excluded:
        add(
            COMPLETED,
            "left",
            "excluded",
            "Excluded by the experimenter",
            remaining & marked,
            f"excluded in {PARTICIPANTS_FILE} (--exclude-excluded)",
        )
        remaining &= ~marked
    reviews = tables.get("reviews")
    if reviews is None:
        remarks.append(
            f"no {REVIEWS_FILE} given: rejections are known only from Prolific's status "
            f"(prolific_status REJECTED in {PARTICIPANTS_FILE})"
        )
    rejected = ids.isin(rejected_participants(reviews, participants, REVIEWS_FILE))
    if not include_rejected:
        add(
            COMPLETED,
            "left",
            "rejected",
            "Submission rejected",
            remaining & rejected,
            f"decision rejected in {REVIEWS_FILE}, or prolific_status REJECTED",
        )
        remaining &= ~rejected
    flagged = _flags(tables.get("quality"), ids, FLAGS, remarks)
    for flag in exclude_flagged:
        chosen = remaining & flagged[flag]
        add(
            COMPLETED,
            "left",
            f"flagged_{flag}",
            f"Flagged {flag}",
            chosen,
            f"flagged {flag} in {QUALITY_FILE} (--exclude-flagged), not excluded above",
        )
        remaining &= ~chosen
    add(
        COMPLETED,
        "left",
        "no_sessions",
        "No learning session in the export",
        remaining & people["sessions"].eq(0),
        "completed, but no row in sessions.csv",
    )

    unfinished = set(counted_ids) - set(ids[completed])
    added_sessions = int(counted_ids.isin(unfinished).sum())
    if include_unfinished:
        boxes.append(
            FlowBox(
                COMPLETED,
                "added",
                "unfinished_taught",
                "did not complete, their taught sessions counted",
                len(unfinished),
                added_sessions,
                "--include-unfinished: participants who did not complete the study with a taught "
                "session (at least one episode or action); only those sessions are counted",
            )
        )
    analysed = people["participant_id"].isin(set(counted_ids))
    if include_rejected:
        add(
            ANALYSED,
            "counted",
            "rejected_counted",
            "rejected (--include-rejected)",
            analysed & rejected,
            f"decision rejected in {REVIEWS_FILE}, or prolific_status REJECTED",
        )
    if not exclude_excluded:
        add(
            ANALYSED,
            "counted",
            "excluded_counted",
            "excluded by the experimenter",
            analysed & marked,
            f"excluded in {PARTICIPANTS_FILE}",
        )
    for flag in FLAGS:
        if flag not in exclude_flagged:
            add(
                ANALYSED,
                "counted",
                f"flagged_{flag}_counted",
                f"flagged {flag}",
                analysed & flagged[flag],
                f"flagged {flag} in {QUALITY_FILE} (--exclude-flagged {flag} drops them)",
            )
    boxes.append(
        FlowBox(
            ANALYSED,
            "stage",
            ANALYSED,
            STAGE_LABELS[ANALYSED],
            int(counted_ids.nunique()),
            len(counted_ids),
            "participants with a learning session Table 1 counts, and those sessions "
            "(the sum of its Total Sessions)",
        )
    )
    order = {name: number for number, name in enumerate(STAGES)}
    kinds = {"stage": 0, "left": 1, "added": 2, "counted": 1}
    boxes.sort(key=lambda b: (order[b.stage], kinds[b.kind]))
    return ParticipantFlow(tuple(boxes), tuple(remarks))


def _erasures(frame: pd.DataFrame | None, remarks: list[str]) -> pd.DataFrame:
    """One row per erasure: the learning sessions it erased, whether it came after consent
    (it erased learning sessions) and who asked (``erased_by``)."""
    if frame is None:
        remarks.append(f"no {ERASURES_FILE} given: withdrawals (data erased) are not counted")
        return pd.DataFrame({"sessions": [], "after_consent": [], "by": []})
    sessions = pd.Series(0, index=frame.index)
    if "learning_sessions_rows" in frame.columns:
        sessions = pd.to_numeric(frame["learning_sessions_rows"], errors="coerce").fillna(0)
        after = sessions.gt(0)
    else:
        remarks.append(
            f"{ERASURES_FILE} has no learning_sessions_rows column: every withdrawal is counted "
            "as after consent"
        )
        after = pd.Series(True, index=frame.index)
    by = (
        frame["erased_by"].astype(str).str.strip().str.lower()
        if "erased_by" in frame.columns
        else pd.Series("", index=frame.index)
    )
    return pd.DataFrame(
        {"sessions": sessions.astype(int), "after_consent": after.astype(bool), "by": by}
    ).reset_index(drop=True)


def _flags(
    quality: pd.DataFrame | None, ids: pd.Series, flags: Sequence[str], remarks: list[str]
) -> dict[str, pd.Series]:
    """Per quality check, which of the participants ``ids`` ``quality.csv`` flags with it."""
    none = {flag: pd.Series(False, index=ids.index) for flag in flags}
    if quality is None or not {"participant_id", "flags"} <= set(quality.columns):
        remarks.append(
            f"no readable {QUALITY_FILE} with the columns participant_id and flags: the quality "
            "checks are not counted"
        )
        return none
    words = dict(
        zip(
            quality["participant_id"].astype(str).str.strip(),
            quality["flags"].fillna("").astype(str).str.split(),
            strict=True,
        )
    )
    found = ids.map(lambda participant: set(words.get(participant, ())))
    return {flag: found.map(lambda named, flag=flag: flag in named).astype(bool) for flag in flags}
