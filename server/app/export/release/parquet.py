"""Parquet files on the Hugging Face Hub's layout: ``data/<file>.parquet`` for every export
table and the feedback table (``release.feedback``), typed from the data dictionary, and a
dataset card (``README.md``) whose YAML header names a config per file with its features, the
licence and the tags, and whose text gives the files, their rows and the RAI summary. A folder
``datasets.load_dataset`` reads, by config, or ``load_dataset("parquet", data_files=...)``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from server.app.export.columns import BOOL, FILES, INT, NUMBER, TIME, Column
from server.app.export.release import About, file_description
from server.app.export.release.feedback import DESCRIPTION, FEEDBACK, LIST_COLUMNS, feedback_frame

ARROW = {
    INT: pa.int64(),
    NUMBER: pa.float64(),
    BOOL: pa.bool_(),
    TIME: pa.timestamp("us", tz="UTC"),
    "text": pa.string(),
}
# The Hub's names of the same types (a card's dataset_info features).
HUB_TYPES = {
    INT: "int64",
    NUMBER: "float64",
    BOOL: "bool",
    TIME: "timestamp[us, tz=UTC]",
    "text": "string",
}
# SPDX ids -> the Hub's licence ids, for those it names.
HUB_LICENCES = {
    "CC-BY-4.0": "cc-by-4.0",
    "CC-BY-SA-4.0": "cc-by-sa-4.0",
    "CC-BY-NC-4.0": "cc-by-nc-4.0",
    "CC0-1.0": "cc0-1.0",
    "ODbL-1.0": "odbl",
    "MIT": "mit",
    "Apache-2.0": "apache-2.0",
}


def _cells(values: pd.Series, column: Column, lists: bool) -> pa.Array:
    if lists and column.name in LIST_COLUMNS:
        item = pa.int64() if LIST_COLUMNS[column.name] == "int64" else pa.string()
        return pa.array(list(values), pa.list_(item))
    if column.kind == TIME:
        return pa.array(pd.to_datetime(values, utc=True, format="ISO8601"), ARROW[TIME])
    if column.kind == NUMBER:
        return pa.array(pd.to_numeric(values), ARROW[NUMBER], from_pandas=True)
    cells = [None if pd.isna(cell) else cell for cell in values]
    if column.kind == "text":
        # A text column of the dictionary holds text (a figure of quality.csv, written as text).
        cells = [cell if cell is None or isinstance(cell, str) else str(cell) for cell in cells]
    return pa.array(cells, ARROW[column.kind])


def arrow_table(frame: pd.DataFrame, columns: tuple[Column, ...]) -> pa.Table:
    lists = columns is FEEDBACK
    return pa.table({column.name: _cells(frame[column.name], column, lists) for column in columns})


def hub_features(columns: tuple[Column, ...]) -> list[dict[str, Any]]:
    features: list[dict[str, Any]] = []
    for column in columns:
        if columns is FEEDBACK and column.name in LIST_COLUMNS:
            features.append({"name": column.name, "list": LIST_COLUMNS[column.name]})
        else:
            features.append({"name": column.name, "dtype": HUB_TYPES[column.kind]})
    return features


def tables(about: About) -> dict[str, tuple[tuple[Column, ...], pd.DataFrame, str]]:
    """file -> its columns, rows and description: the export's, then the feedback."""
    found = {name: (FILES[name], about.tables[name], file_description(name)) for name in FILES}
    found["feedback"] = (FEEDBACK, feedback_frame(about.tables), DESCRIPTION)
    return found


def _yaml(value: Any, indent: int = 0) -> list[str]:
    """``value`` (dicts, lists, strings, numbers) as YAML block lines; strings as JSON's,
    which YAML reads as they are."""
    pad = " " * indent
    if isinstance(value, dict):
        lines: list[str] = []
        for key, item in value.items():
            if isinstance(item, dict | list) and item:
                lines.append(f"{pad}{key}:")
                lines += _yaml(item, indent + 2)
            else:
                lines.append(f"{pad}{key}: {json.dumps(item, ensure_ascii=False)}")
        return lines
    if isinstance(value, list):
        lines = []
        for item in value:
            inner = _yaml(item, indent + 2)
            lines.append(f"{pad}- {inner[0].lstrip()}")
            lines += inner[1:]
        return lines
    return [f"{pad}{json.dumps(value, ensure_ascii=False)}"]


def card(about: About, found: dict[str, tuple[tuple[Column, ...], pd.DataFrame, str]]) -> str:
    header: dict[str, Any] = {"pretty_name": about.title}
    licence = about.answer("license")
    if licence:
        header["license"] = HUB_LICENCES.get(licence, "other")
        if licence not in HUB_LICENCES:
            header["license_name"] = licence
    header["tags"] = ["human-feedback", "learning-from-demonstration", "croissant", *about.keywords]
    header["task_categories"] = ["reinforcement-learning"]
    # The Hub's loader refuses a split with no rows: an empty table's file is there (its
    # columns typed), but it is no config.
    loadable = {name: entry for name, entry in found.items() if len(entry[1])}
    header["configs"] = [
        {"config_name": name, "data_files": [{"split": "train", "path": f"data/{name}.parquet"}]}
        for name in loadable
    ]
    header["dataset_info"] = [
        {
            "config_name": name,
            "features": hub_features(columns),
            "splits": [{"name": "train", "num_examples": len(frame)}],
        }
        for name, (columns, frame, _) in loadable.items()
    ]
    lines = ["---", *_yaml(header), "---", "", f"# {about.title}", "", about.description, ""]
    lines += ["## Files", "", "| config | rows | what a row is |", "| --- | ---: | --- |"]
    lines += [f"| `{name}` | {len(frame)} | {text} |" for name, (_, frame, text) in found.items()]
    lines += [
        "",
        "Each config is one file, `data/<config>.parquet`; its columns are described in the "
        "data dictionary (the CSV export's `data_dictionary.csv`). A file with no rows is no "
        "config (the Hub's loader refuses an empty split): read it with pandas or pyarrow. "
        "`feedback` is the "
        "participants' + and - in the unpaired-preference shape (`prompt`, `completion`, "
        "`label`), with the state and trajectory so far.",
        "",
        "```python",
        "from datasets import load_dataset",
        'feedback = load_dataset("<this folder or repository>", "feedback", split="train")',
        "```",
        "",
        "## Responsible AI (Croissant RAI)",
        "",
    ]
    for key, value in about.rai().items():
        shown = ", ".join(value) if isinstance(value, list) else str(value)
        lines.append(f"- **{key}**: {shown}")
    unanswered = about.unanswered()
    if unanswered:
        lines += [
            "",
            "Not answered by the authors (the study file's `[dataset]` table): "
            + ", ".join(unanswered)
            + ".",
        ]
    citation = about.answer("citation")
    if citation:
        lines += ["", "## Citation", "", "```", citation, "```"]
    return "\n".join(lines) + "\n"


def write(about: About, out: Path) -> list[Path]:
    """The Hub's layout in ``out``: ``README.md`` and ``data/*.parquet``."""
    data = out / "data"
    data.mkdir(parents=True, exist_ok=True)
    found = tables(about)
    written = []
    for name, (columns, frame, _) in found.items():
        path = data / f"{name}.parquet"
        pq.write_table(arrow_table(frame, columns), path)
        written.append(path)
    readme = out / "README.md"
    readme.write_text(card(about, found))
    return [readme, *written]
