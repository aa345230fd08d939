"""A Frictionless Data Package (``datapackage.json``, Data Package v1 as Zenodo and Dataverse
read it) over the export's CSVs in the same folder: one resource per CSV, its Table Schema
from the data dictionary (each column's type and description), empty cells as missing values,
the primary keys and the foreign keys between the files (``release.PRIMARY_KEYS``,
``release.FOREIGN_KEYS``)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from server.app.export.columns import BOOL, FILES, INT, NUMBER, TIME, Column
from server.app.export.release import FOREIGN_KEYS, PRIMARY_KEYS, About, file_description

FILE = "datapackage.json"
# A dictionary kind -> its Table Schema field.
TYPES: dict[str, dict[str, Any]] = {
    INT: {"type": "integer"},
    NUMBER: {"type": "number"},
    BOOL: {"type": "boolean", "trueValues": ["True"], "falseValues": ["False"]},
    TIME: {"type": "datetime"},  # ISO 8601 with its offset (+00:00)
    "text": {"type": "string"},
}
LICENCE_URLS = {
    "CC-BY-4.0": "https://creativecommons.org/licenses/by/4.0/",
    "CC0-1.0": "https://creativecommons.org/publicdomain/zero/1.0/",
    "ODbL-1.0": "https://opendatacommons.org/licenses/odbl/1-0/",
    "CC-BY-SA-4.0": "https://creativecommons.org/licenses/by-sa/4.0/",
    "CC-BY-NC-4.0": "https://creativecommons.org/licenses/by-nc/4.0/",
}


def table_field(column: Column) -> dict[str, Any]:
    return {"name": column.name, "description": column.description, **TYPES[column.kind]}


def table_schema(name: str) -> dict[str, Any]:
    schema: dict[str, Any] = {
        "fields": [table_field(column) for column in FILES[name]],
        "missingValues": [""],
    }
    if name in PRIMARY_KEYS:
        schema["primaryKey"] = list(PRIMARY_KEYS[name])
    keys = [key for key in FOREIGN_KEYS if key.file == name]
    if keys:
        schema["foreignKeys"] = [
            {
                "fields": list(key.columns),
                "reference": {"resource": key.to, "fields": list(key.to_columns)},
            }
            for key in keys
        ]
    return schema


def resource(name: str, path: Path) -> dict[str, Any]:
    content = path.read_bytes()
    return {
        "name": name,
        "path": path.name,
        "profile": "tabular-data-resource",
        "format": "csv",
        "mediatype": "text/csv",
        "encoding": "utf-8",
        "description": file_description(name),
        "bytes": len(content),
        "hash": f"sha256:{hashlib.sha256(content).hexdigest()}",
        "schema": table_schema(name),
    }


def package(about: About, folder: Path) -> dict[str, Any]:
    """The descriptor of the CSVs in ``folder``."""
    descriptor: dict[str, Any] = {
        "profile": "tabular-data-package",
        "name": "bam-study-data",
        "title": about.title,
        "description": about.description,
        "created": about.exported_at.isoformat(),
        "keywords": list(about.keywords),
        "resources": [resource(name, folder / f"{name}.csv") for name in FILES],
    }
    licence = about.answer("license")
    if licence:
        entry = {"name": licence}
        if licence in LICENCE_URLS:
            entry["path"] = LICENCE_URLS[licence]
        descriptor["licenses"] = [entry]
    if about.authors:
        descriptor["contributors"] = [{"title": name, "role": "author"} for name in about.authors]
    url = about.answer("url")
    if url:
        descriptor["homepage"] = url
    version = about.answer("version")
    if version:
        descriptor["version"] = version
    return descriptor


def write(about: About, out: Path) -> list[Path]:
    """``datapackage.json`` beside the CSVs ``export.files.write_export`` wrote in ``out``."""
    path = out / FILE
    path.write_text(json.dumps(package(about, out), indent=2, ensure_ascii=False) + "\n")
    return [path]
