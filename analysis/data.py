"""Reading and validating a study's exported data.

``load_tables`` reads an export folder (``bam-study export``) and returns two validated
tables, the learning sessions and their evaluations. ``validate_tables`` does the checking
and typing on tables given as data frames, so that another reader (a database, for example)
can feed the same analysis. Every problem is an ``InputError`` whose message names the file,
the row and the column.

Empty episodes are not counted. Before the study server refused to start an episode on its
task's goal, letting the agent try while it stood on the goal recorded an agent episode of one
action that ended at once, on the goal where it began (``end_reason`` goal, ``start_state`` =
``end_state``), and queued an update for it. Nothing was taught, but each counted as an
episode (and an action) towards "episodes required". Where the episodes table is given, such
episodes are taken out of the cumulative counts of the evaluations from their update on.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd

from analysis.names import LEARNERS
from analysis.options import InputError

SESSIONS_FILE = "sessions.csv"
EVALUATIONS_FILE = "evaluations.csv"
PARTICIPANTS_FILE = "participants.csv"
EPISODES_FILE = "episodes.csv"
EPISODE_COLUMNS = (
    "session_id",
    "kind",
    "start_state",
    "end_state",
    "end_reason",
    "actions",
    "update_index",
)

SESSION_COLUMNS = (
    "session_id",
    "participant_id",
    "domain",
    "environment",
    "learner",
    "position",
    "started_at",
    "finished_at",
    "completed",
)
EVALUATION_COLUMNS = (
    "session_id",
    "participant_id",
    "domain",
    "environment",
    "learner",
    "position",
    "update_index",
    "episodes",
    "actions",
    "normalized_return",
)
# Columns of an evaluation that must agree with its learning session.
SHARED_COLUMNS = ("participant_id", "domain", "environment", "learner", "position")

# A policy can be exactly optimal; exact scoring can overshoot 1.0 by rounding only.
RETURN_TOLERANCE = 1e-6

_TRUE = {"true", "t", "yes", "y", "1"}
_FALSE = {"false", "f", "no", "n", "0"}


def load_tables(
    data_dir: Path | str,
    *,
    exclude_excluded: bool = False,
    notes: list[str] | None = None,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Read and validate an export folder: ``(sessions, evaluations)``.

    With ``exclude_excluded``, the learning sessions of participants whose ``status`` in
    ``participants.csv`` is ``excluded`` are dropped. Remarks for the reader of the results
    (how many sessions were excluded, for example) are appended to ``notes``.
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
    if participants_path.exists():
        try:
            participants = read_csv(participants_path)
        except InputError as error:
            if exclude_excluded:
                raise
            # Only --exclude-excluded needs it; otherwise it is looked at for a remark only.
            if notes is not None:
                notes.append(f"participant statuses not checked: {error}")
    elif exclude_excluded:
        raise InputError(f"--exclude-excluded needs {PARTICIPANTS_FILE}, which is not in {folder}")
    episodes_path = folder / EPISODES_FILE
    episodes = read_csv(episodes_path) if episodes_path.exists() else None
    return validate_tables(
        sessions,
        evaluations,
        participants=participants,
        episodes=episodes,
        exclude_excluded=exclude_excluded,
        notes=notes,
    )


def load_database(
    url: str,
    *,
    exclude_excluded: bool = False,
    notes: list[str] | None = None,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Read and validate a study database directly: the tables ``bam-study export`` would
    write, taken from the database at ``url`` (SQLite or PostgreSQL). See ``load_tables``."""
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError, SQLAlchemyError

    from server.app.export.tables import load_tables as read_database
    from server.app.export.tables import open_study_database
    from server.app.storage.db import current_revision, head_revision

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
        tables = read_database(db, pseudonymize=False)
    except SQLAlchemyError as error:
        message = str(error).strip().splitlines()[0]
        raise InputError(f"--database-url {shown}: cannot read the database: {message}") from None
    finally:
        db.dispose()
    return validate_tables(
        tables["sessions"],
        tables["evaluations"],
        participants=tables["participants"],
        episodes=tables["episodes"],
        exclude_excluded=exclude_excluded,
        notes=notes,
        sources=(
            "the sessions table",
            "the evaluations table",
            "the participants table",
            "the episodes table",
        ),
    )


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
    exclude_excluded: bool = False,
    notes: list[str] | None = None,
    sources: tuple[str, str, str, str] = (
        SESSIONS_FILE,
        EVALUATIONS_FILE,
        PARTICIPANTS_FILE,
        EPISODES_FILE,
    ),
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Check and type the learning sessions and evaluations; see ``load_tables``. With
    ``episodes``, empty episodes are taken out of the evaluations' counts (module docstring);
    without, the counts are taken as they are, and a note says so.

    ``sources`` name the four tables in messages (file names, or table names for a
    database). Rows are counted from 1 in the order given.
    """
    sessions_source, evaluations_source, participants_source, episodes_source = sources
    notes = notes if notes is not None else []
    sessions = _validate_sessions(sessions.reset_index(drop=True), sessions_source)
    evaluations = _validate_evaluations(
        evaluations.reset_index(drop=True), evaluations_source, sessions, sessions_source, notes
    )

    excluded = _excluded_participants(participants, participants_source, exclude_excluded)
    if excluded is not None:
        dropped = sessions["participant_id"].isin(excluded)
        if exclude_excluded:
            people = int(sessions.loc[dropped, "participant_id"].nunique())
            notes.append(
                f"excluded {_count(int(dropped.sum()), 'learning session')} of "
                f"{_count(people, 'participant')} marked excluded in {participants_source}"
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
                f"{_count(int(dropped.sum()), 'learning session')} of participants marked "
                f"excluded in {participants_source} are included (--exclude-excluded drops them)"
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


def _count(number: int, noun: str) -> str:
    return f"{number} {noun}{'' if number == 1 else 's'}"


def _validate_sessions(frame: pd.DataFrame, source: str) -> pd.DataFrame:
    _require_columns(frame, SESSION_COLUMNS, source)
    if frame.empty:
        raise InputError(f"{source}: no learning sessions (the file has a header only)")
    out = pd.DataFrame(index=frame.index)
    for column in ("session_id", "participant_id", "environment", "learner"):
        out[column] = _text(frame, column, source)
    out["domain"] = _optional_text(frame["domain"])
    out["position"] = _integer(frame, "position", source)
    out["started_at"] = _optional_text(frame["started_at"])
    out["finished_at"] = _optional_text(frame["finished_at"])
    out["completed"] = _boolean(frame, "completed", source)
    _check_known_learners(out, source)
    duplicated = out["session_id"].duplicated(keep="first")
    if duplicated.any():
        row = int(np.flatnonzero(duplicated.to_numpy())[0])
        first = int(np.flatnonzero((out["session_id"] == out.at[row, "session_id"]).to_numpy())[0])
        _fail(
            source,
            row,
            "session_id",
            f"learning session {out.at[row, 'session_id']!r} appears again "
            f"(first at {_where(source, first)})",
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
    _require_columns(frame, EVALUATION_COLUMNS, source)
    # The study server exports failed learner updates too (status "failed", no return):
    # they are checked like the others but have no evaluation to analyse.
    failed = pd.Series(False, index=frame.index)
    if "status" in frame.columns:
        failed = frame["status"].astype(str).str.strip().str.lower().eq("failed")
        if failed.any():
            frame = frame.copy()
            frame.loc[failed, "normalized_return"] = "0"
    out = pd.DataFrame(index=frame.index)
    for column in ("session_id", "participant_id", "environment", "learner"):
        out[column] = _text(frame, column, source)
    out["domain"] = _optional_text(frame["domain"])
    for column in ("position", "update_index", "episodes", "actions"):
        out[column] = _integer(frame, column, source)
    out["normalized_return"] = _number(frame, "normalized_return", source)
    outside = (out["normalized_return"] < 0) | (out["normalized_return"] > 1.0 + RETURN_TOLERANCE)
    if outside.any():
        row = int(np.flatnonzero(outside.to_numpy())[0])
        _fail(
            source,
            row,
            "normalized_return",
            f"{_raw(frame, 'normalized_return')[0].iloc[row]} is outside [0, 1] "
            "(a normalised return is a fraction of the optimal return)",
            int(outside.sum()),
        )
    _check_known_learners(out, source)

    # Every evaluation belongs to a known learning session and agrees with it.
    by_id = sessions.set_index("session_id")
    unknown = ~out["session_id"].isin(by_id.index)
    if unknown.any():
        row = int(np.flatnonzero(unknown.to_numpy())[0])
        _fail(
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
            _fail(
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
        _fail(
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
            _fail(
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
            f"{_count(int(failed.sum()), 'failed learner update')} in {source} left out "
            "(no evaluation; the server's log says why)"
        )
    return out.loc[~failed, list(EVALUATION_COLUMNS)].reset_index(drop=True)


def empty_episodes(episodes: pd.DataFrame, source: str = EPISODES_FILE) -> pd.Series:
    """Which episodes are empty (module docstring): agent episodes of one action that ended
    at the goal where they began."""
    _require_columns(episodes, EPISODE_COLUMNS, source)
    start, start_missing = _raw(episodes, "start_state")
    end, _ = _raw(episodes, "end_state")
    kind, _ = _raw(episodes, "kind")
    reason, _ = _raw(episodes, "end_reason")
    actions, _ = _raw(episodes, "actions")
    return (
        (kind == "agent") & (reason == "goal") & (actions == "1") & ~start_missing & (start == end)
    )


def discount_empty_episodes(
    evaluations: pd.DataFrame, episodes: pd.DataFrame, source: str, notes: list[str]
) -> pd.DataFrame:
    """The evaluations with empty episodes taken out of their cumulative counts: an empty
    episode ended by update u takes one episode and its action from every evaluation of its
    session from update u on. Episodes of sessions that have no evaluations here (tutorials,
    sessions left out) are ignored."""
    empty = empty_episodes(episodes, source)
    session_ids, _ = _raw(episodes, "session_id")
    empty &= session_ids.isin(set(evaluations["session_id"]))
    if not empty.any():
        return evaluations
    text, _ = _raw(episodes, "update_index")
    numbers = pd.to_numeric(text, errors="coerce")
    bad = empty & ~((numbers >= 0) & (numbers == np.round(numbers)))
    _first_bad(
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
        f"{_count(count, 'empty episode')} in {_count(sessions, 'learning session')} not "
        "counted (an agent's try from the goal that ended there at once: one action, "
        "start_state = end_state, end_reason goal; the server no longer records these)"
    )
    return out


def _excluded_participants(
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
        marked |= participants["excluded"].astype(str).str.strip().str.lower().isin(_TRUE)
    if "status" in participants.columns:
        marked |= participants["status"].astype(str).str.strip().str.lower() == "excluded"
    return set(participants.loc[marked, "participant_id"].astype(str).str.strip())


def _require_columns(frame: pd.DataFrame, columns: tuple[str, ...], source: str) -> None:
    missing = [column for column in columns if column not in frame.columns]
    if missing:
        found = ", ".join(repr(str(c)) for c in frame.columns) or "none"
        raise InputError(
            f"{source}: missing column(s) {', '.join(repr(c) for c in missing)} (found: {found})"
        )


def _where(source: str, row: int) -> str:
    """Row ``row`` (0-based, in the table's order) as a reader finds it: rows count from 1,
    and in a CSV file the header is line 1."""
    if source.endswith(".csv"):
        return f"{source}, row {row + 1} (line {row + 2})"
    return f"{source}, row {row + 1}"


def _fail(source: str, row: int, column: str, message: str, count: int = 1) -> None:
    more = f" (and {count - 1} more such row{'s' if count > 2 else ''})" if count > 1 else ""
    raise InputError(f"{_where(source, row)}, column {column!r}: {message}{more}")


def _raw(frame: pd.DataFrame, column: str) -> tuple[pd.Series, pd.Series]:
    """The column as stripped strings, and where it is missing (empty, NaN or None)."""
    values = frame[column]
    missing = values.isna()
    text = values.astype(object).where(~missing, "").map(str).str.strip()
    return text, missing | (text == "")


def _first_bad(
    frame: pd.DataFrame, column: str, source: str, bad: pd.Series, describe: Callable[[str], str]
) -> None:
    if bad.any():
        row = int(np.flatnonzero(bad.to_numpy())[0])
        text, _ = _raw(frame, column)
        _fail(source, row, column, describe(text.iloc[row]), int(bad.sum()))


def _check_missing(frame: pd.DataFrame, column: str, source: str) -> pd.Series:
    text, missing = _raw(frame, column)
    _first_bad(frame, column, source, missing, lambda _: "missing value")
    return text


def _text(frame: pd.DataFrame, column: str, source: str) -> pd.Series:
    return _check_missing(frame, column, source)


def _optional_text(values: pd.Series) -> pd.Series:
    return values.astype(object).where(values.notna(), "").map(str).str.strip()


def _number(frame: pd.DataFrame, column: str, source: str) -> pd.Series:
    text = _check_missing(frame, column, source)
    numbers = pd.to_numeric(text, errors="coerce").astype(float)
    bad = ~np.isfinite(numbers)
    _first_bad(frame, column, source, bad, lambda value: f"{value!r} is not a number")
    return numbers


def _integer(frame: pd.DataFrame, column: str, source: str) -> pd.Series:
    numbers = _number(frame, column, source)
    fractional = numbers != np.round(numbers)
    _first_bad(frame, column, source, fractional, lambda value: f"{value} is not a whole number")
    negative = numbers < 0
    _first_bad(frame, column, source, negative, lambda value: f"{value} is negative")
    return numbers.astype(np.int64)


def _boolean(frame: pd.DataFrame, column: str, source: str) -> pd.Series:
    text = _check_missing(frame, column, source).str.lower()
    bad = ~text.isin(_TRUE | _FALSE)
    _first_bad(frame, column, source, bad, lambda value: f"{value!r} is not true or false")
    return text.isin(_TRUE)


def _check_known_learners(frame: pd.DataFrame, source: str) -> None:
    unknown = ~frame["learner"].isin(list(LEARNERS))
    if unknown.any():
        row = int(np.flatnonzero(unknown.to_numpy())[0])
        _fail(
            source,
            row,
            "learner",
            f"unknown learner {frame.at[row, 'learner']!r} (known: {', '.join(LEARNERS)})",
            int(unknown.sum()),
        )
