"""Reading and validating a study's exported data.

``load_tables`` reads an export folder (``bam-study export``) and returns two validated
tables, the learning sessions and their evaluations. ``validate_tables`` does the checking
and typing on tables given as data frames, so that another reader (a database, for example)
can feed the same analysis. Every problem is an ``InputError`` whose message names the file,
the row and the column.

Table 1 counts the learning sessions of the participants who completed the study (as the
paper's section 5 did: 58 of the 129 who began); ``include_unfinished`` adds the taught
sessions (those with at least one episode or action) of the participants who did not. A note says how
many sessions were left out and why (``analysis.selection``).

Empty episodes are not counted. Before the study server refused to start an episode on its
task's goal, letting the agent try while it stood on the goal recorded an agent episode of one
action that ended at once, on the goal where it began (``end_reason`` goal, ``start_state`` =
``end_state``), and queued an update for it. Nothing was taught, but each counted as an
episode (and an action) towards "episodes required". Where the episodes table is given, such
episodes are taken out of the cumulative counts of the evaluations from their update on.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from analysis import cells
from analysis.columns import (
    EPISODES_FILE,
    ERASURES_FILE,
    EVALUATION_COLUMNS,
    EVALUATIONS_FILE,
    PARTICIPANTS_FILE,
    QUALITY_FILE,
    REVIEWS_FILE,
    SESSION_COLUMNS,
    SESSIONS_FILE,
    SHARED_COLUMNS,
)
from analysis.names import LEARNERS
from analysis.options import InputError
from analysis.selection import (
    COMPLETED_STATUSES,
    apply_rejections,
    count_phrase,
    discount_empty_episodes,
    drop_flagged,
    excluded_participants,
    flagged_participants,
    keep_finished,
    rejected_participants,
)
from server.app.storage.vocabulary import UpdateStatus

# The tables the participant flow reads (``load_tables``' ``tables``).
FLOW_TABLES = ("participants", "sessions", "reviews", "quality", "erasures")

# A policy can be exactly optimal; exact scoring can overshoot 1.0 by rounding only.
RETURN_TOLERANCE = 1e-6


def load_tables(
    data_dir: Path | str,
    *,
    exclude_excluded: bool = False,
    include_unfinished: bool = False,
    include_rejected: bool = False,
    exclude_flagged: tuple[str, ...] = (),
    notes: list[str] | None = None,
    tables: dict[str, pd.DataFrame | None] | None = None,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Read and validate an export folder: ``(sessions, evaluations)``.

    Only the learning sessions of participants who completed the study are kept (their
    ``status`` in ``participants.csv``); with ``include_unfinished``, also the taught sessions
    of those who did not. With ``exclude_excluded``, the learning sessions of participants the
    experimenter excluded are dropped; with ``exclude_flagged``, those of the participants
    ``quality.csv`` flags with any of those checks. The sessions of participants whose
    submission was rejected (``reviews.csv``, or Prolific's status) are left out unless
    ``include_rejected``. Remarks for the reader of the results (how many sessions were left
    out and why, for example) are appended to ``notes``; the tables as read (``participants``,
    ``sessions``, ``reviews``, ``quality``, ``erasures``; None for a file not given) are put
    into ``tables``, for the participant flow (``analysis.flow``).
    """
    folder = Path(data_dir)
    if not folder.exists():
        raise InputError(f"export folder {folder} does not exist")
    if not folder.is_dir():
        raise InputError(f"export folder {folder} is not a folder")
    sessions = read_csv(folder / SESSIONS_FILE)
    evaluations = read_csv(folder / EVALUATIONS_FILE)
    participants_path = folder / PARTICIPANTS_FILE
    participants = None
    unreadable = None
    if participants_path.exists():
        try:
            participants = read_csv(participants_path)
        except InputError as error:
            if exclude_excluded:
                raise
            unreadable = str(error)  # then every session is counted, and a note says why
    elif exclude_excluded:
        raise InputError(f"--exclude-excluded needs {PARTICIPANTS_FILE}, which is not in {folder}")
    episodes_path = folder / EPISODES_FILE
    episodes = read_csv(episodes_path) if episodes_path.exists() else None
    quality = None
    if exclude_flagged:
        if not (folder / QUALITY_FILE).exists():
            raise InputError(f"--exclude-flagged needs {QUALITY_FILE}, which is not in {folder}")
        quality = read_csv(folder / QUALITY_FILE)
    reviews_path = folder / REVIEWS_FILE
    reviews = read_csv(reviews_path) if reviews_path.exists() else None
    if tables is not None:
        tables.update(
            participants=participants,
            sessions=sessions,
            reviews=reviews,
            quality=quality if quality is not None else _optional_csv(folder / QUALITY_FILE),
            erasures=_optional_csv(folder / ERASURES_FILE),
        )
    notes = notes if notes is not None else []
    sessions, evaluations = validate_tables(
        sessions,
        evaluations,
        participants=participants,
        episodes=episodes,
        reviews=reviews,
        exclude_excluded=exclude_excluded,
        include_unfinished=include_unfinished,
        include_rejected=include_rejected,
        notes=notes,
        participants_unreadable=unreadable,
    )
    if not exclude_flagged:
        return sessions, evaluations
    assert quality is not None
    flagged = flagged_participants(quality, exclude_flagged, QUALITY_FILE)
    return drop_flagged(sessions, evaluations, flagged, exclude_flagged, QUALITY_FILE, notes)


def load_database(
    url: str,
    *,
    exclude_excluded: bool = False,
    include_unfinished: bool = False,
    include_rejected: bool = False,
    exclude_flagged: tuple[str, ...] = (),
    notes: list[str] | None = None,
    tables: dict[str, pd.DataFrame | None] | None = None,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Read and validate a study database directly: the tables ``bam-study export`` would
    write, taken from the database at ``url`` (SQLite or PostgreSQL). See ``load_tables``."""
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError, SQLAlchemyError

    from server.app.export.tables import export_tables as read_database
    from server.app.storage.db import current_revision, head_revision, open_study_database

    try:
        shown = make_url(url).render_as_string(hide_password=True)
    except ArgumentError as error:
        raise InputError(f"--database-url {url!r} is not a database URL: {error}") from None
    try:
        # Read-only for SQLite: no empty database left for a wrong path, no journal change.
        db = open_study_database(url)
    except (FileNotFoundError, ValueError, ArgumentError, ImportError) as error:
        raise InputError(f"--database-url {shown}: {error}") from None
    try:
        current, head = current_revision(db.engine), head_revision()
        if current != head:
            raise InputError(
                f"--database-url {shown}: the schema is at revision {current or 'none'}, not "
                f"{head}: not a study database, or one that `bam-study db upgrade` must bring "
                "up to date first"
            )
        read = read_database(db, pseudonymize=False)
    except SQLAlchemyError as error:
        message = str(error).strip().splitlines()[0]
        raise InputError(f"--database-url {shown}: cannot read the database: {message}") from None
    finally:
        db.dispose()
    if tables is not None:
        tables.update({name: read[name] for name in FLOW_TABLES})
    notes = notes if notes is not None else []
    sessions, evaluations = validate_tables(
        read["sessions"],
        read["evaluations"],
        participants=read["participants"],
        episodes=read["episodes"],
        reviews=read["reviews"],
        exclude_excluded=exclude_excluded,
        include_unfinished=include_unfinished,
        include_rejected=include_rejected,
        notes=notes,
        sources=(
            "the sessions table",
            "the evaluations table",
            "the participants table",
            "the episodes table",
        ),
        reviews_source="the reviews table",
    )
    if not exclude_flagged:
        return sessions, evaluations
    source = "the quality checks"
    flagged = flagged_participants(read["quality"], exclude_flagged, source)
    return drop_flagged(sessions, evaluations, flagged, exclude_flagged, source, notes)


def _optional_csv(path: Path) -> pd.DataFrame | None:
    """A file the participant flow reads if it is there and readable (None otherwise: the
    flow then says what it could not count)."""
    if not path.exists():
        return None
    try:
        return read_csv(path)
    except InputError:
        return None


def read_csv(path: Path) -> pd.DataFrame:
    """A CSV file with a header as a table of strings (nothing converted yet)."""
    if not path.exists():
        raise InputError(f"{path.name} not found in {path.parent}")
    if not path.is_file():
        raise InputError(f"{path} is not a file")
    try:
        frame = pd.read_csv(
            path, dtype=str, keep_default_na=False, na_filter=False, encoding="utf-8-sig"
        )
    except pd.errors.EmptyDataError:
        raise InputError(f"{path.name}: the file is empty (no header line)") from None
    except (pd.errors.ParserError, UnicodeDecodeError) as error:
        raise InputError(f"{path.name}: not a readable CSV file: {str(error).strip()}") from None
    frame.columns = [str(column).strip() for column in frame.columns]
    return frame.reset_index(drop=True)


def validate_tables(
    sessions: pd.DataFrame,
    evaluations: pd.DataFrame,
    *,
    participants: pd.DataFrame | None = None,
    episodes: pd.DataFrame | None = None,
    reviews: pd.DataFrame | None = None,
    exclude_excluded: bool = False,
    include_unfinished: bool = False,
    include_rejected: bool = False,
    notes: list[str] | None = None,
    participants_unreadable: str | None = None,
    sources: tuple[str, str, str, str] = (
        SESSIONS_FILE,
        EVALUATIONS_FILE,
        PARTICIPANTS_FILE,
        EPISODES_FILE,
    ),
    reviews_source: str = REVIEWS_FILE,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Check and type the learning sessions and evaluations; see ``load_tables``. With
    ``episodes``, empty episodes are taken out of the evaluations' counts (module docstring);
    without, the counts are taken as they are, and a note says so. Without ``participants``
    (or without its ``status`` column), every learning session is counted, and a note says
    why (``participants_unreadable``: the error that kept the caller from reading it). The
    sessions of participants whose submission was rejected (``reviews``, or
    ``participants``' ``prolific_status``) are left out unless ``include_rejected``.

    ``sources`` name the four tables in messages (file names, or table names for a
    database). Rows are counted from 1 in the order given.
    """
    sessions_source, evaluations_source, participants_source, episodes_source = sources
    notes = notes if notes is not None else []
    sessions = _validate_sessions(sessions.reset_index(drop=True), sessions_source)
    evaluations = _validate_evaluations(
        evaluations.reset_index(drop=True), evaluations_source, sessions, sessions_source, notes
    )

    excluded = excluded_participants(participants, participants_source, exclude_excluded)
    if excluded is not None:
        dropped = sessions["participant_id"].isin(excluded)
        if exclude_excluded:
            people = int(sessions.loc[dropped, "participant_id"].nunique())
            notes.append(
                f"excluded {count_phrase(int(dropped.sum()), 'learning session')} of "
                f"{count_phrase(people, 'participant')} marked excluded in {participants_source}"
            )
            sessions = sessions.loc[~dropped].reset_index(drop=True)
            evaluations = evaluations.loc[
                evaluations["session_id"].isin(sessions["session_id"])
            ].reset_index(drop=True)
            if sessions.empty:
                raise InputError(
                    f"{sessions_source}: no learning sessions are left after excluding the "
                    f"participants marked excluded in {participants_source}"
                )
        elif dropped.any():
            notes.append(
                f"{count_phrase(int(dropped.sum()), 'learning session')} of participants marked "
                f"excluded in {participants_source} are included (--exclude-excluded drops them)"
            )
    sessions, evaluations = keep_finished(
        sessions,
        evaluations,
        participants,
        participants_source,
        include_unfinished=include_unfinished,
        notes=notes,
        unreadable=participants_unreadable,
    )
    if sessions.empty:
        raise InputError(
            f"{sessions_source}: no learning sessions of participants who completed the study "
            f"(status {' or '.join(COMPLETED_STATUSES)} in {participants_source}); "
            "--include-unfinished adds the taught sessions of those who did not"
        )
    sessions, evaluations = apply_rejections(
        sessions,
        evaluations,
        rejected_participants(reviews, participants, reviews_source),
        include_rejected=include_rejected,
        reviews_source=reviews_source,
        notes=notes,
    )
    if episodes is None:
        notes.append(
            f"no {episodes_source} given: episodes and actions are counted as the evaluations "
            "give them (empty episodes, a try that ended at once on the goal, not looked for)"
        )
    else:
        evaluations = discount_empty_episodes(
            evaluations, episodes.reset_index(drop=True), episodes_source, notes
        )
    return sessions, evaluations


def _validate_sessions(frame: pd.DataFrame, source: str) -> pd.DataFrame:
    cells.require_columns(frame, SESSION_COLUMNS, source)
    if frame.empty:
        raise InputError(f"{source}: no learning sessions (the file has a header only)")
    out = pd.DataFrame(index=frame.index)
    for column in ("session_id", "participant_id", "environment", "learner"):
        out[column] = cells.text(frame, column, source)
    out["domain"] = cells.optional_text(frame["domain"])
    out["position"] = cells.integer(frame, "position", source)
    out["started_at"] = cells.optional_text(frame["started_at"])
    out["finished_at"] = cells.optional_text(frame["finished_at"])
    out["completed"] = cells.boolean(frame, "completed", source)
    _check_known_learners(out, source)
    duplicated = out["session_id"].duplicated(keep="first")
    if duplicated.any():
        row = int(np.flatnonzero(duplicated.to_numpy())[0])
        first = int(np.flatnonzero((out["session_id"] == out.at[row, "session_id"]).to_numpy())[0])
        cells.fail(
            source,
            row,
            "session_id",
            f"learning session {out.at[row, 'session_id']!r} appears again "
            f"(first at {cells.where(source, first)})",
            int(duplicated.sum()),
        )
    return out[list(SESSION_COLUMNS)]


def _validate_evaluations(
    frame: pd.DataFrame,
    source: str,
    sessions: pd.DataFrame,
    sessions_source: str,
    notes: list[str],
) -> pd.DataFrame:
    cells.require_columns(frame, EVALUATION_COLUMNS, source)
    # The study server exports failed learner updates too (status "failed", no return):
    # they are checked like the others but have no evaluation to analyse.
    failed = pd.Series(False, index=frame.index)
    if "status" in frame.columns:
        failed = frame["status"].astype(str).str.strip().str.lower().eq(UpdateStatus.FAILED)
        if failed.any():
            frame = frame.copy()
            frame.loc[failed, "normalized_return"] = "0"
    out = pd.DataFrame(index=frame.index)
    for column in ("session_id", "participant_id", "environment", "learner"):
        out[column] = cells.text(frame, column, source)
    out["domain"] = cells.optional_text(frame["domain"])
    for column in ("position", "update_index", "episodes", "actions"):
        out[column] = cells.integer(frame, column, source)
    out["normalized_return"] = cells.number(frame, "normalized_return", source)
    outside = (out["normalized_return"] < 0) | (out["normalized_return"] > 1.0 + RETURN_TOLERANCE)
    if outside.any():
        row = int(np.flatnonzero(outside.to_numpy())[0])
        cells.fail(
            source,
            row,
            "normalized_return",
            f"{cells.raw(frame, 'normalized_return')[0].iloc[row]} is outside [0, 1] "
            "(a normalised return is a fraction of the optimal return)",
            int(outside.sum()),
        )
    _check_known_learners(out, source)

    # Every evaluation belongs to a known learning session and agrees with it.
    by_id = sessions.set_index("session_id")
    unknown = ~out["session_id"].isin(by_id.index)
    if unknown.any():
        row = int(np.flatnonzero(unknown.to_numpy())[0])
        cells.fail(
            source,
            row,
            "session_id",
            f"learning session {out.at[row, 'session_id']!r} is not in {sessions_source}",
            int(unknown.sum()),
        )
    for column in SHARED_COLUMNS:
        expected = out["session_id"].map(by_id[column])
        differs = out[column] != expected
        if column == "domain":  # only when both files give one
            differs &= (out[column] != "") & (expected != "")
        if differs.any():
            row = int(np.flatnonzero(differs.to_numpy())[0])
            cells.fail(
                source,
                row,
                column,
                f"{out.at[row, column]!r} differs from {expected.iloc[row]!r} given for "
                f"learning session {out.at[row, 'session_id']!r} in {sessions_source}",
                int(differs.sum()),
            )

    duplicated = out.duplicated(["session_id", "update_index"], keep="first")
    if duplicated.any():
        row = int(np.flatnonzero(duplicated.to_numpy())[0])
        cells.fail(
            source,
            row,
            "update_index",
            f"update {out.at[row, 'update_index']} of learning session "
            f"{out.at[row, 'session_id']!r} appears twice",
            int(duplicated.sum()),
        )

    # Cumulative counts never go down as the updates go on.
    ordered = out.sort_values(["session_id", "update_index"], kind="stable")
    grouped = ordered.groupby("session_id", sort=False)
    previous_update = grouped["update_index"].shift()
    for column in ("episodes", "actions"):
        previous = grouped[column].shift()
        decreasing = ordered[column] < previous
        if decreasing.any():
            row = int(decreasing[decreasing].index.min())
            cells.fail(
                source,
                row,
                column,
                f"{out.at[row, column]} at update {out.at[row, 'update_index']} of learning "
                f"session {out.at[row, 'session_id']!r} is less than {int(previous[row])} at "
                f"update {int(previous_update[row])} (cumulative counts cannot decrease)",
                int(decreasing.sum()),
            )
    if failed.any():
        notes.append(
            f"{count_phrase(int(failed.sum()), 'failed learner update')} in {source} left out "
            "(no evaluation; the server's log says why)"
        )
    return out.loc[~failed, list(EVALUATION_COLUMNS)].reset_index(drop=True)


def _check_known_learners(frame: pd.DataFrame, source: str) -> None:
    unknown = ~frame["learner"].isin(list(LEARNERS))
    if unknown.any():
        row = int(np.flatnonzero(unknown.to_numpy())[0])
        cells.fail(
            source,
            row,
            "learner",
            f"unknown learner {frame.at[row, 'learner']!r} (known: {', '.join(LEARNERS)})",
            int(unknown.sum()),
        )
