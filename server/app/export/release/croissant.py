"""Croissant 1.0 JSON-LD (``croissant.json``, with the Responsible-AI fields of Croissant RAI
1.0) over the export's CSVs in the same folder: the distribution (every CSV with its SHA-256),
a record set per file whose fields are typed and described by the data dictionary, with
its primary key (``release.PRIMARY_KEYS``), the data package's foreign keys as the fields'
``references`` (``REFERENCES``: all but two, which mlcroissant cannot read), and the RAI
fields (``About.rai``). ``mlcroissant`` loads it and reads every record set."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from server.app.export.columns import BOOL, FILES, INT, NUMBER, TIME, Column
from server.app.export.release import FOREIGN_KEYS, PRIMARY_KEYS, About, file_description

FILE = "croissant.json"
DATA_TYPES = {
    INT: "sc:Integer",
    NUMBER: "sc:Float",
    BOOL: "sc:Boolean",
    TIME: "sc:DateTime",
    "text": "sc:Text",
}
CONTEXT: dict[str, Any] = {
    "@language": "en",
    "@vocab": "https://schema.org/",
    "citeAs": "cr:citeAs",
    "column": "cr:column",
    "conformsTo": "dct:conformsTo",
    "cr": "http://mlcommons.org/croissant/",
    "rai": "http://mlcommons.org/croissant/RAI/",
    "data": {"@id": "cr:data", "@type": "@json"},
    "dataType": {"@id": "cr:dataType", "@type": "@vocab"},
    "dct": "http://purl.org/dc/terms/",
    "equivalentProperty": "cr:equivalentProperty",
    "examples": {"@id": "cr:examples", "@type": "@json"},
    "extract": "cr:extract",
    "field": "cr:field",
    "fileProperty": "cr:fileProperty",
    "fileObject": "cr:fileObject",
    "fileSet": "cr:fileSet",
    "format": "cr:format",
    "includes": "cr:includes",
    "isLiveDataset": "cr:isLiveDataset",
    "jsonPath": "cr:jsonPath",
    "key": "cr:key",
    "md5": "cr:md5",
    "parentField": "cr:parentField",
    "path": "cr:path",
    "recordSet": "cr:recordSet",
    "references": "cr:references",
    "regex": "cr:regex",
    "repeated": "cr:repeated",
    "replace": "cr:replace",
    "samplingRate": "cr:samplingRate",
    "sc": "https://schema.org/",
    "separator": "cr:separator",
    "source": "cr:source",
    "subField": "cr:subField",
    "transform": "cr:transform",
}


# The record sets other record sets refer to (participants, sessions, tutorial_sessions).
REFERRED = frozenset(key.to for key in FOREIGN_KEYS)
# (record set, field) -> the field it refers to: the data package's foreign keys, but those
# from a record set that is referred to itself (sessions' and tutorial_sessions' participant_id):
# mlcroissant (1.1.1) reads a field's references as a join with the referred record set, and a
# join with a record set that joins too fails (it is handed that record set's records, not its
# table), so that the referring record sets could not be read.
REFERENCES = {
    (key.file, column): f"{key.to}/{to}"
    for key in FOREIGN_KEYS
    if key.file not in REFERRED
    for column, to in zip(key.columns, key.to_columns, strict=True)
}


def record_field(name: str, column: Column) -> dict[str, Any]:
    entry: dict[str, Any] = {
        "@type": "cr:Field",
        "@id": f"{name}/{column.name}",
        "name": column.name,
        "description": column.description,
        "dataType": DATA_TYPES[column.kind],
        "source": {"fileObject": {"@id": f"{name}.csv"}, "extract": {"column": column.name}},
    }
    referred = REFERENCES.get((name, column.name))
    if referred is not None:
        entry["references"] = {"field": {"@id": referred}}
    return entry


def record_set(name: str) -> dict[str, Any]:
    entry: dict[str, Any] = {
        "@type": "cr:RecordSet",
        "@id": name,
        "name": name,
        "description": file_description(name),
        "field": [record_field(name, column) for column in FILES[name]],
    }
    if name in PRIMARY_KEYS:
        entry["key"] = [{"@id": f"{name}/{column}"} for column in PRIMARY_KEYS[name]]
    return entry


def file_object(name: str, path: Path) -> dict[str, Any]:
    content = path.read_bytes()
    return {
        "@type": "cr:FileObject",
        "@id": path.name,
        "name": path.name,
        "description": file_description(name),
        "contentUrl": path.name,
        "contentSize": f"{len(content)} B",
        "encodingFormat": "text/csv",
        "sha256": hashlib.sha256(content).hexdigest(),
    }


def metadata(about: About, folder: Path) -> dict[str, Any]:
    """The JSON-LD of the CSVs in ``folder``."""
    files = [*FILES, "data_dictionary"]
    document: dict[str, Any] = {
        "@context": CONTEXT,
        "@type": "sc:Dataset",
        "conformsTo": [
            "http://mlcommons.org/croissant/1.0",
            "http://mlcommons.org/croissant/RAI/1.0",
        ],
        "name": about.title,
        "description": about.description,
        "datePublished": about.exported_at.date().isoformat(),
        "keywords": list(about.keywords),
        "distribution": [file_object(name, folder / f"{name}.csv") for name in files],
        "recordSet": [record_set(name) for name in FILES],
        **about.rai(),
    }
    for key in ("license", "url", "version"):
        given = about.answer(key)
        if given:
            document[key] = given
    if about.authors:
        document["creator"] = [{"@type": "sc:Person", "name": name} for name in about.authors]
    citation = about.answer("citation")
    if citation:
        document["citeAs"] = citation
    unanswered = about.unanswered()
    if unanswered:
        # Said where a reader looks, since Croissant has no field for a question left open.
        document["description"] += (
            " Not answered by the authors (the study file's [dataset] table): "
            + ", ".join(unanswered)
            + "."
        )
    return document


def write(about: About, out: Path) -> list[Path]:
    """``croissant.json`` beside the CSVs ``export.files.write_export`` wrote in ``out``."""
    path = out / FILE
    path.write_text(json.dumps(metadata(about, out), indent=2, ensure_ascii=False) + "\n")
    return [path]
