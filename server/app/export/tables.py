"""The study's data as tables: ``export_tables`` reads a study database (the analysis can use it
directly) into one pandas DataFrame per exported file, its columns as ``export.columns``
describes them. ``export.files`` writes them as CSVs with ``data_dictionary.csv``, or a zip.

Worker and assignment ids are pseudonymised (``rights.pseudonyms``: HMAC-SHA256 with
``BAM_SECRET``, or the random secret created with the database) and completion codes left out,
unless ``pseudonymize=False``.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import pandas as pd

from server.app.export.columns import (
    ATTENTION_CHECKS,
    BONUSES,
    EPISODES,
    ERASURES,
    EVALUATIONS,
    EVENTS,
    INT,
    MESSAGES,
    PARTICIPANTS,
    QUESTIONNAIRE_ANSWERS,
    REVIEWS,
    SESSIONS,
    STATUS_CHANGES,
    TUTORIAL_SESSIONS,
    Column,
)
from server.app.export.quality import quality_table
from server.app.export.read import Context, read_study
from server.app.rights.pseudonyms import database_secret
from server.app.storage.db import Database, open_study_database
from server.app.storage.vocabulary import SessionKind


def table_frame(columns: Sequence[Column], rows: Iterable[Any], context: Context) -> pd.DataFrame:
    """One file's table: a row per row, a column per column (integer columns as Int64)."""
    cells = [[column.read(row, context) for column in columns] for row in rows]
    table = pd.DataFrame(cells, columns=[column.name for column in columns])
    for column in columns:
        if column.kind == INT:
            table[column.name] = table[column.name].astype("Int64")
    return table


def export_tables(
    db: Database | str, pseudonymize: bool = True, secret: str | None = None
) -> dict[str, pd.DataFrame]:
    """Every export table as a DataFrame (columns as in ``columns.DICTIONARY``; times as ISO
    strings), from a study database or its URL."""
    if isinstance(db, str):
        database = open_study_database(db)
        try:
            return export_tables(database, pseudonymize, secret)
        finally:
            database.dispose()
    if pseudonymize and secret is None:
        secret = database_secret(db)
    study = read_study(db)
    context = Context.of(study, pseudonymize, secret)
    files: dict[str, tuple[Sequence[Column], Iterable[Any]]] = {
        "participants": (PARTICIPANTS, study.participants),
        "sessions": (SESSIONS, (x for x in study.sessions if x.kind == SessionKind.STUDY)),
        "tutorial_sessions": (
            TUTORIAL_SESSIONS,
            (x for x in study.sessions if x.kind == SessionKind.TUTORIAL),
        ),
        "episodes": (EPISODES, study.episodes),
        "events": (EVENTS, study.events),
        "evaluations": (
            EVALUATIONS,
            (u for u in study.updates if context.session(u.session_id).kind == SessionKind.STUDY),
        ),
        "status_changes": (STATUS_CHANGES, study.changes),
        "questionnaire_answers": (QUESTIONNAIRE_ANSWERS, study.answers),
        "reviews": (REVIEWS, study.reviews),
        "bonuses": (BONUSES, study.bonuses),
        "messages": (MESSAGES, study.messages),
        "attention_checks": (ATTENTION_CHECKS, study.checks),
        "erasures": (ERASURES, study.erasures),
    }
    tables = {name: table_frame(columns, rows, context) for name, (columns, rows) in files.items()}
    tables["quality"] = quality_table(tables)
    return tables
