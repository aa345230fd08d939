"""A Psych-DS folder (schema 1.5.0): ``dataset_description.json`` (schema.org JSON-LD, a
``Dataset`` with its ``name``, ``description`` and ``variableMeasured``: every column of every
file, from the data dictionary), ``README.md``, and the export's CSVs under ``data/`` named by
Psych-DS keywords (``study-<Study>_description-<file>_data.csv``), each with a sidecar
(``..._data.json``) whose ``variableMeasured`` is that file's own columns: one column name
can mean different things in two files (``status``), and a sidecar replaces the dataset's
list for its file only.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

from server.app.export.columns import FILES, Column
from server.app.export.files import csv_text
from server.app.export.release import About, file_description

SCHEMA_VERSION = "1.5.0"
DESCRIPTION_FILE = "dataset_description.json"
UNIT = {"minutes": "minutes", "update_seconds": "seconds"}


def keyword_value(text: str) -> str:
    """A keyword's value: letters and digits only (Psych-DS), the words joined in camel case."""
    words = [word for word in re.split(r"[^A-Za-z0-9]+", text) if word]
    value = words[0] + "".join(word[:1].upper() + word[1:] for word in words[1:]) if words else ""
    return value[:40] or "study"


def data_file(about: About, name: str) -> str:
    return f"study-{keyword_value(about.title)}_description-{keyword_value(name)}_data.csv"


def variable(column: Column, description: str | None = None) -> dict[str, Any]:
    entry = {
        "@type": "PropertyValue",
        "name": column.name,
        "description": description or column.description,
    }
    if column.name in UNIT:
        entry["unitText"] = UNIT[column.name]
    return entry


def variables() -> list[dict[str, Any]]:
    """Every column name once: its description, or each file's when files mean different
    things by it."""
    meanings: dict[str, dict[str, str]] = {}
    first: dict[str, Column] = {}
    for name, columns in FILES.items():
        for column in columns:
            first.setdefault(column.name, column)
            meanings.setdefault(column.name, {})[name] = column.description
    found = []
    for column_name, by_file in meanings.items():
        texts = set(by_file.values())
        description = (
            next(iter(texts))
            if len(texts) == 1
            else " ".join(f"In {file}.csv: {text}" for file, text in by_file.items())
        )
        found.append(variable(first[column_name], description))
    return found


def description(about: About) -> dict[str, Any]:
    document: dict[str, Any] = {
        "@context": "https://schema.org/",
        "@type": "Dataset",
        "name": about.title,
        "description": about.description,
        "schemaVersion": SCHEMA_VERSION,
        "keywords": list(about.keywords),
        "variableMeasured": variables(),
        "dateCreated": about.exported_at.isoformat(),
        "usageInfo": about.personal_information(),
    }
    if about.authors:
        document["author"] = [{"@type": "Person", "name": name} for name in about.authors]
    for key in ("citation", "license", "url", "version"):
        given = about.answer(key)
        if given:
            document[key] = given
    return document


def sidecar(name: str) -> dict[str, Any]:
    return {
        "description": file_description(name),
        "variableMeasured": [variable(column) for column in FILES[name]],
    }


def readme(about: About) -> str:
    lines = [f"# {about.title}", "", about.description, "", "## Files", ""]
    lines += [f"- `data/{data_file(about, name)}`: {file_description(name)}" for name in FILES]
    unanswered = about.unanswered()
    if unanswered:
        lines += ["", "Not answered by the authors: " + ", ".join(unanswered) + "."]
    return "\n".join(lines) + "\n"


def write(about: About, out: Path) -> list[Path]:
    """The Psych-DS folder ``out``."""
    data = out / "data"
    data.mkdir(parents=True, exist_ok=True)
    written = [out / DESCRIPTION_FILE, out / "README.md"]
    written[0].write_text(json.dumps(description(about), indent=2, ensure_ascii=False) + "\n")
    written[1].write_text(readme(about))
    for name in FILES:
        path = data / data_file(about, name)
        path.write_bytes(csv_text(about.tables[name]).encode())
        side = path.with_suffix(".json")
        side.write_text(json.dumps(sidecar(name), indent=2, ensure_ascii=False) + "\n")
        written += [path, side]
    return written
