"""The export's tables written out: CSV files and ``data_dictionary.csv`` in a folder
(``write_export``) or a zip (``export_zip``), every text cell guarded so that no spreadsheet
runs it as a formula and no line break inside it splits its row (``csv_text``).
"""

from __future__ import annotations

import io
import zipfile
from pathlib import Path
from typing import Any

import pandas as pd

from server.app.export.columns import DICTIONARY

DESCRIPTIONS = {
    "participants": "One row per participant (an arrival that was not a preview).",
    "sessions": "One row per learning session of the study (the tutorial's are apart).",
    "tutorial_sessions": "One row per tutorial learning session (not analysed).",
    "episodes": "One row per episode of every learning session, tutorials included.",
    "events": "One row per acknowledged participant request, in order (append-only log).",
    "evaluations": "One row per processed learner update of the study's sessions.",
    "status_changes": "One row per change of a participant's status.",
    "questionnaire_answers": "One row per question answered in the post-study questionnaire "
    "(an optional question left unanswered has none; a study without a questionnaire, none).",
    "reviews": "One row per submitted MTurk assignment or Prolific submission the "
    "experimenter approved or rejected.",
    "bonuses": "One row per bonus the experimenter paid (or asked the platform to pay).",
    "messages": "One row per participant messaged through Prolific (bam-study prolific "
    "message), for each message Prolific took; a refused message has none.",
    "attention_checks": "One row per instructional attention check of a participant (the "
    "study file's [attention_checks]; none without it): move the robot to the star.",
    "quality": "One row per participant who completed: quality checks built for teaching "
    "(completion time against the others', idle stretches, optimal demonstrations, consistent "
    "feedback, attention checks failed) and the rejection ground, if any, that Prolific accepts for them. None rejects "
    "anybody by itself.",
    "erasures": "One row per participant whose data was erased (withdrawal or request): the "
    "other files hold nothing of theirs; remove their rows (by participant_id or pseudonym) "
    "from copies exported before.",
    "data_dictionary": "Every file's columns. In every file, each line of a text cell that "
    "begins with =, +, -, @, a tab or a carriage return is written with an apostrophe (') "
    "before it, so that a spreadsheet shows it as text instead of running it as a formula; "
    "remove the apostrophe that begins each such line to get the text as stored. A text cell "
    "that holds a line break (any of Unicode's) is in double quotes. Numbers are written as "
    "they are.",
}
FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r")
# What str.splitlines splits on; "\n" ends the rows.
OTHER_LINE_BREAKS = "\r\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029"


def dictionary_frame() -> pd.DataFrame:
    """``data_dictionary.csv``: every file's columns, then every file's description."""
    rows = [
        {"file": f"{name}.csv", "column": column, "description": description}
        for name, columns in DICTIONARY.items()
        for column, description in columns.items()
    ]
    rows += [
        {"file": f"{name}.csv", "column": "", "description": text}
        for name, text in DESCRIPTIONS.items()
    ]
    return pd.DataFrame(rows, columns=["file", "column", "description"])


def as_text(value: Any) -> Any:
    """A text cell no line of which a spreadsheet will run as a formula (``DESCRIPTIONS``)."""
    if not isinstance(value, str):
        return value
    lines = value.splitlines(keepends=True)
    if not any(line.startswith(FORMULA_STARTS) for line in lines):
        return value
    return "".join("'" + line if line.startswith(FORMULA_STARTS) else line for line in lines)


def neutralised(frame: pd.DataFrame) -> pd.DataFrame:
    text = [name for name in frame.columns if pd.api.types.is_string_dtype(frame[name].dtype)]
    if not text:
        return frame
    frame = frame.copy()
    for name in text:
        frame[name] = frame[name].map(as_text)
    return frame


def csv_text(frame: pd.DataFrame) -> str:
    """``frame`` as CSV, its text cells guarded (``as_text``) and every cell holding a line
    break in quotes, so that no reader splits its row. The csv module quotes a cell holding a
    character of the line terminator only: the rows are written ended by every line break, and
    each such ending outside quotes then becomes "\\n"."""
    row_end = "\n" + OTHER_LINE_BREAKS
    pieces = neutralised(frame).to_csv(index=False, lineterminator=row_end).split(row_end)
    text, quoted = [], False
    for piece in pieces[:-1]:
        quoted ^= piece.count('"') % 2 == 1  # a quote inside quotes is doubled
        text += [piece, row_end if quoted else "\n"]
    text.append(pieces[-1])
    return "".join(text)


def export_files(tables: dict[str, pd.DataFrame]) -> dict[str, bytes]:
    """File name -> content: each table's CSV and ``data_dictionary.csv``."""
    files = {f"{name}.csv": csv_text(frame).encode() for name, frame in tables.items()}
    files["data_dictionary.csv"] = csv_text(dictionary_frame()).encode()
    return files


def write_export(tables: dict[str, pd.DataFrame], out: Path) -> list[Path]:
    """Write the CSVs and the data dictionary into ``out``; returns the files written."""
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, content in export_files(tables).items():
        path = out / name
        path.write_bytes(content)
        written.append(path)
    return written


def export_zip(tables: dict[str, pd.DataFrame]) -> bytes:
    """The files of ``export_files`` in a zip."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, content in export_files(tables).items():
            archive.writestr(name, content)
    return buffer.getvalue()
