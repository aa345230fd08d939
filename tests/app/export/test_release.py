"""The study's data as a release, each format checked by its own standard's tool: the
Frictionless data package validates with its foreign keys (and a broken reference fails it);
mlcroissant loads the Croissant file, with those keys as references, and reads every record
set with the CSVs' row counts; ``datasets`` reads every Parquet table with the same counts, by
file and by the card's configs; the Psych-DS folder passes the 1.5.0 schema's required-field
and file-name rules (vendored in tests/app/export/psych_ds/, with their source). The RAI
fields hold what the server knows, the [dataset] table's answers, and list the questions it
leaves open; they are named as the Croissant RAI vocabulary (vendored in
tests/app/export/croissant_rai/, with its source) defines them. After `bam-study erase`,
every format still validates and none holds the erased participant.

One small study (two simulated participants) is run once for the module."""

from __future__ import annotations

import csv
import json
import re
import shutil
import sqlite3
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import pandas as pd
import pytest
from fastapi.testclient import TestClient

from server.app.export.columns import DICTIONARY, FILES, INT
from server.app.export.release import FOREIGN_KEYS, HUMAN_ANSWERS
from server.app.export.release.feedback import FEEDBACK
from server.app.export.release.psych_ds import DESCRIPTION_FILE
from server.app.main import create_app
from server.app.storage.db import Database
from server.app.study_file import DEFAULT_STUDY_CONFIG, load_study_config
from server.commands.main import main
from server.commands.simulated import SimulatedParticipant, TeachingPlan
from tests.support.databases import migrated_sqlite
from tests.support.server import ADMIN_TOKEN, make_settings, study_config, wait_for_updates

PLAN = TeachingPlan(min_rounds=1, max_rounds=1, agent_try_probability=1.0, max_agent_steps=6)
RAI_VOCABULARY = Path(__file__).parent / "croissant_rai" / "croissant_rai.ttl"
PSYCH_DS = json.loads((Path(__file__).parent / "psych_ds" / "schema-1.5.0-rules.json").read_text())
DATASET_TABLE = """
[dataset]
title = "Teaching robots in grid worlds"
license = "CC-BY-4.0"
url = "https://example.org/bam-data"
version = "1.0.0"
authors = ["A. Author", "B. Author"]
citation = "Author, A. and Author, B. (2026). Teaching robots in grid worlds."
annotator_demographics = "Adults on MTurk in the United States."
biases = "Crowd workers who chose a game-like task."
limitations = "Every participant of this test is simulated."
"""
EXCLUSION = "did not follow the instructions"


@pytest.fixture(autouse=True)
def hub_offline(monkeypatch: pytest.MonkeyPatch) -> None:
    """``datasets`` and the Hub's client offline, whenever they were imported: the tests read
    local files only."""
    import datasets.config
    import huggingface_hub.constants

    for name in ("HF_DATASETS_OFFLINE", "HF_HUB_OFFLINE"):
        monkeypatch.setenv(name, "1")
        monkeypatch.setattr(datasets.config, name, True)
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)


@pytest.fixture(scope="module")
def study(tmp_path_factory: pytest.TempPathFactory, executor: ProcessPoolExecutor) -> str:
    """A SQLite study database with two participants who taught every agent, the agents'
    tries judged with + and -, the first excluded; its URL."""
    url = migrated_sqlite(tmp_path_factory.mktemp("study") / "study.db")
    db = Database.from_url(url)
    try:
        app = create_app(make_settings(url), study_config(), db=db, executor=executor)
        with TestClient(app) as client:
            runs = [
                SimulatedParticipant(
                    "http://testserver", index, 11, PLAN, client=TestClient(client.app)
                ).take_part()
                for index in range(2)
            ]
            assert [run.error for run in runs] == [None, None]
            wait_for_updates(db)
            excluded = client.post(
                "/api/admin/participants/1/exclusion",
                json={"reason": EXCLUSION},
                headers={"Authorization": f"Bearer {ADMIN_TOKEN}"},
            )
            assert excluded.status_code == 200, excluded.text
    finally:
        db.dispose()
    return url


def study_file(folder: Path, dataset: str = DATASET_TABLE) -> Path:
    path = folder / "study.toml"
    path.write_text(DEFAULT_STUDY_CONFIG.read_text() + dataset)
    return path


def export_all(url: str, out: Path, study_path: Path, *flags: str) -> Path:
    args = ["export", "--database-url", url, "--out", str(out), "--study", str(study_path)]
    assert main([*args, "--format", "all", *flags]) == 0
    return out


@pytest.fixture(scope="module")
def release(study: str, tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("release")
    return export_all(study, folder / "export", study_file(folder))


def csv_rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="", encoding="utf-8") as file:
        return list(csv.DictReader(file))


def row_counts(out: Path) -> dict[str, int]:
    return {name: len(csv_rows(out / f"{name}.csv")) for name in FILES}


# Frictionless
def check_data_package(out: Path) -> None:
    from frictionless import Package, validate

    report = validate(out / "datapackage.json")
    assert report.valid, report.flatten(["rowNumber", "fieldName", "type", "message"])
    package = Package(out / "datapackage.json")
    counts = row_counts(out)
    for resource in package.resources:
        columns = DICTIONARY[resource.name]
        assert [f.name for f in resource.schema.fields] == list(columns)
        assert [f.description for f in resource.schema.fields] == list(columns.values())
        assert len(resource.read_rows()) == counts[resource.name], resource.name
    assert {r.name for r in package.resources} == set(FILES)


def test_the_data_package_validates_with_its_foreign_keys(release: Path) -> None:
    check_data_package(release)
    package = json.loads((release / "datapackage.json").read_text())
    schemas = {resource["name"]: resource["schema"] for resource in package["resources"]}
    assert schemas["participants"]["primaryKey"] == ["participant_id"]
    declared = {
        (
            name,
            tuple(key["fields"]),
            key["reference"]["resource"],
            tuple(key["reference"]["fields"]),
        )
        for name, schema in schemas.items()
        for key in schema.get("foreignKeys", [])
    }
    for name in ("sessions", "episodes", "events", "evaluations", "reviews", "bonuses"):
        assert (name, ("participant_id",), "participants", ("participant_id",)) in declared, name
    for name in ("episodes", "events", "evaluations"):
        assert (name, ("session_id",), "sessions", ("session_id",)) in declared, name
    for name in ("episodes", "events"):
        assert (name, ("tutorial_session_id",), "tutorial_sessions", ("session_id",)) in declared
    assert package["licenses"][0]["name"] == "CC-BY-4.0"


def broken_copy(release: Path, folder: Path, file: str, edit: Any) -> Any:
    """The release's data package with ``file``'s rows changed by ``edit`` (a DataFrame of
    text cells -> the rows kept), its checksums left out; frictionless's report of it."""
    from frictionless import validate

    shutil.copytree(release, folder, ignore=shutil.ignore_patterns("psych-ds", "hugging-face"))
    rows = pd.read_csv(folder / f"{file}.csv", dtype=str, keep_default_na=False)
    edit(rows).to_csv(folder / f"{file}.csv", index=False)
    package = json.loads((release / "datapackage.json").read_text())
    for resource in package["resources"]:
        resource.pop("hash")
        resource.pop("bytes")
    (folder / "datapackage.json").write_text(json.dumps(package))
    return validate(folder / "datapackage.json")


def foreign_key_errors(report: Any) -> set[tuple[str, str, str, str]]:
    """(file, its columns, the file referred to, the value) of each foreign-key error;
    asserts that there are errors and no others."""
    assert not report.valid
    found = set()
    for task in report.tasks:
        for error in task.errors:
            assert error.type == "foreign-key", (task.name, error.message)
            columns, value = ",".join(error.field_names), ",".join(error.field_cells)
            found.add((task.name, columns, error.reference_name, value))
    return found


def test_a_session_whose_participant_is_gone_breaks_a_foreign_key(
    release: Path, tmp_path: Path
) -> None:
    def unknown_participant(rows: pd.DataFrame) -> pd.DataFrame:
        rows.loc[0, "participant_id"] = "999"
        return rows

    report = broken_copy(release, tmp_path / "broken", "sessions", unknown_participant)
    assert foreign_key_errors(report) == {("sessions", "participant_id", "participants", "999")}


@pytest.mark.parametrize(
    ("kind", "column"), [("sessions", "session_id"), ("tutorial_sessions", "tutorial_session_id")]
)
def test_an_episode_whose_session_row_is_removed_breaks_a_foreign_key(
    release: Path, tmp_path: Path, kind: str, column: str
) -> None:
    """The session of an episode removed from its file: its episodes, events (and, for a
    study session, evaluations) no longer validate, by that session's column."""
    episodes = csv_rows(release / "episodes.csv")
    gone = next(row[column] for row in episodes if row[column])
    report = broken_copy(
        release, tmp_path / "broken", kind, lambda rows: rows[rows["session_id"] != gone]
    )
    files = {"episodes", "events"} | ({"evaluations"} if kind == "sessions" else set())
    assert foreign_key_errors(report) == {(file, column, kind, gone) for file in files}


# Croissant
def check_croissant(out: Path) -> Any:
    import mlcroissant as mlc

    dataset = mlc.Dataset(jsonld=out / "croissant.json")
    counts = row_counts(out)
    names = [record_set.name for record_set in dataset.metadata.record_sets]
    assert names == list(FILES)
    for name in names:
        assert sum(1 for _ in dataset.records(record_set=name)) == counts[name], name
    return dataset


def test_croissant_reads_every_record_set_with_the_csv_counts_and_its_rai_fields(
    release: Path,
) -> None:
    dataset = check_croissant(release)
    assert dataset.metadata.ctx.issues.warnings == set()  # every recommended field given
    document = json.loads((release / "croissant.json").read_text())
    participants = csv_rows(release / "participants.csv")
    # Every file of the distribution with its checksum.
    import hashlib

    for entry in document["distribution"]:
        content = (release / entry["contentUrl"]).read_bytes()
        assert entry["sha256"] == hashlib.sha256(content).hexdigest()
    fields = {f["name"]: f for f in document["recordSet"][1]["field"]}
    assert fields["participant_id"]["dataType"] == "sc:Integer"
    assert fields["participant_id"]["description"] == DICTIONARY["sessions"]["participant_id"]
    assert document["recordSet"][0]["key"] == [{"@id": "participants/participant_id"}]
    assert fields["completed"]["dataType"] == "sc:Boolean"
    # The server's facts.
    assert dataset.metadata.data_collection.count(f"{len(participants)} participants") == 1
    assert "2 submitted" in document["rai:dataCollection"]
    assert "Amazon Mechanical Turk" in document["rai:dataAnnotationPlatform"]
    assert EXCLUSION in document["rai:dataCollectionMissingData"]
    assert "pseudonymised" in document["rai:personalSensitiveInformation"]
    start, end = document["rai:dataCollectionTimeframe"]
    assert start == min(p["arrived_at"] for p in participants)
    assert end == max(p["last_seen_at"] for p in participants)
    consent = load_study_config(DEFAULT_STUDY_CONFIG).consent.strip()
    assert f"Consent text participants agreed to: {consent}" in document["rai:dataCollection"]
    # The authors' answers, and the open questions listed, not invented.
    assert document["rai:annotatorDemographics"] == "Adults on MTurk in the United States."
    assert document["rai:dataBiases"] == "Crowd workers who chose a game-like task."
    assert document["rai:dataLimitations"].startswith(
        "Every participant of this test is simulated."
    )
    assert "rai:dataUseCases" not in document and "rai:dataSocialImpact" not in document
    assert "Not answered by the authors" in document["description"]
    assert "rai:dataUseCases" in document["description"]
    assert document["license"] == "CC-BY-4.0" and len(document["creator"]) == 2


def test_croissant_fields_reference_the_fields_the_data_package_keys_name(release: Path) -> None:
    """Each single-column foreign key of the data package is a Croissant ``references`` (from
    participants to sessions, episodes, events and the rest), and mlcroissant reads the
    referring record sets with their own values (its join with the referred file adds no
    row and changes no cell)."""
    import mlcroissant as mlc

    document = json.loads((release / "croissant.json").read_text())
    references = {
        field["@id"]: field["references"]["field"]["@id"]
        for record_set in document["recordSet"]
        for field in record_set["field"]
        if "references" in field
    }
    keys = {f"{key.file}/{key.columns[0]}": f"{key.to}/{key.to_columns[0]}" for key in FOREIGN_KEYS}
    # All but the participant_id of the record sets referred to themselves (mlcroissant cannot
    # read a join with a record set that joins too).
    left_out = {"sessions/participant_id", "tutorial_sessions/participant_id"}
    assert references == {field: to for field, to in keys.items() if field not in left_out}
    assert references["events/tutorial_session_id"] == "tutorial_sessions/session_id"
    assert references["episodes/session_id"] == "sessions/session_id"
    dataset = mlc.Dataset(jsonld=release / "croissant.json")
    for name in sorted({key.file for key in FOREIGN_KEYS}):
        rows = csv_rows(release / f"{name}.csv")
        read = list(dataset.records(record_set=name))
        assert len(read) == len(rows), name
        for column in (c.name for c in FILES[name] if c.kind == INT):
            cells = [record[f"{name}/{column}"] for record in read]
            expected = [int(row[column]) if row[column] else None for row in rows]
            assert [None if pd.isna(cell) else int(cell) for cell in cells] == expected, column


def test_every_rai_field_is_spelt_as_the_rai_vocabulary_defines_it(release: Path) -> None:
    """The Croissant RAI 1.0 vocabulary (vendored in tests/app/export/croissant_rai/, with its
    source) defines rai:dataCollectionTimeframe; mlcroissant 1.1.1 reads
    rai:dataCollectionTimeFrame, a spelling of the specification's prose only."""
    import rdflib

    graph = rdflib.Graph().parse(RAI_VOCABULARY, format="turtle")
    namespace = "http://mlcommons.org/croissant/RAI/"
    defined = {
        f"rai:{subject.removeprefix(namespace)}"
        for subject in graph.subjects(rdflib.RDF.type, rdflib.RDF.Property)
        if str(subject).startswith(namespace)
    }
    assert "rai:dataCollectionTimeframe" in defined
    assert "rai:dataCollectionTimeFrame" not in defined
    document = json.loads((release / "croissant.json").read_text())
    written = {key for key in document if key.startswith("rai:")}
    assert "rai:dataCollectionTimeframe" in written
    assert written <= defined, written - defined
    assert set(HUMAN_ANSWERS) <= defined


def test_without_a_dataset_table_the_human_answers_are_listed_as_missing(
    study: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["export", "--database-url", study, "--out", str(tmp_path / "out")]
    path = study_file(tmp_path, dataset="")
    assert main([*args, "--format", "croissant", "--study", str(path)]) == 0
    err = capsys.readouterr().err
    document = json.loads((tmp_path / "out" / "croissant.json").read_text())
    for rai in HUMAN_ANSWERS:
        assert rai not in document
        assert rai in document["description"] and rai in err
    assert "license" not in document and "creator" not in document
    assert document["rai:dataCollection"]  # what the server knows is still said
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted(
        [f"{name}.csv" for name in FILES] + ["data_dictionary.csv", "croissant.json"]
    )


# Parquet and the dataset card
def check_parquet(out: Path, counts: dict[str, int]) -> dict[str, Any]:
    import datasets

    folder = out / "hugging-face"
    loaded = {}
    for name in [*FILES, "feedback"]:
        path = folder / "data" / f"{name}.parquet"
        if name in counts and not counts[name]:  # no config: the Hub refuses an empty split
            assert pd.read_parquet(path).columns.tolist() == list(DICTIONARY[name])
            continue
        table = datasets.load_dataset(
            "parquet",
            data_files=str(path),
            split="train",
            cache_dir=str(out.parent / "hf-cache"),
        )
        if name in counts:
            assert table.num_rows == counts[name], name
            assert table.column_names == list(DICTIONARY[name]), name
        loaded[name] = table
    return loaded


def test_parquet_on_the_hub_layout_reads_with_datasets(release: Path) -> None:
    import datasets

    loaded = check_parquet(release, row_counts(release))
    participants = loaded["participants"]
    assert participants.features["participant_id"].dtype == "int64"
    assert participants.features["excluded"].dtype == "bool"
    assert str(participants.features["arrived_at"].dtype).startswith("timestamp")
    # The card's configs, read as the Hub reads them.
    card = (release / "hugging-face" / "README.md").read_text()
    header = card.split("---")[1]
    import yaml

    meta = yaml.safe_load(header)
    assert meta["license"] == "cc-by-4.0"
    counts = row_counts(release)
    assert [c["config_name"] for c in meta["configs"]] == [
        *(name for name in FILES if counts[name]),
        "feedback",
    ]
    events = datasets.load_dataset(
        str(release / "hugging-face"),
        "events",
        split="train",
        cache_dir=str(release.parent / "hf-cache"),
    )
    assert events.num_rows == len(csv_rows(release / "events.csv"))
    assert "rai:dataCollection" in card and "rai:dataUseCases" in card  # the open question


def test_the_feedback_table_holds_every_plus_and_minus_with_its_trajectory(release: Path) -> None:
    feedback = pd.read_parquet(release / "hugging-face" / "data" / "feedback.parquet")
    events = pd.read_csv(release / "events.csv")
    given = events[events["record"] == "feedback"]
    assert len(given) > 0
    assert list(feedback.columns) == [column.name for column in FEEDBACK]
    assert list(feedback["event_id"]) == list(given["event_id"])
    assert list(feedback["label"]) == list(given["feedback"] > 0)
    steps = events.set_index("event_id")
    episodes = pd.read_csv(release / "episodes.csv").set_index("episode_id")
    for row in feedback.itertuples():
        step = steps.loc[row.step_event_id]
        assert step["record"] == "agent_step"
        for column in ("session_id", "tutorial_session_id"):  # the same, or both empty
            given, of_step = getattr(row, column), step[column]
            assert pd.isna(given) == pd.isna(of_step), column
            assert pd.isna(given) or int(given) == int(of_step), column
        assert row.session_kind == episodes.loc[row.episode_id, "session_kind"]
        assert (row.state, row.action, row.next_state) == (
            step["state"],
            step["action"],
            step["next_state"],
        )
        assert row.step_event_id < row.event_id
        assert list(row.states)[-1] == row.state and len(row.states) == len(row.actions) + 1
        assert row.states[0] == episodes.loc[row.episode_id, "start_state"]
        assert row.completion == row.action and row.prompt.endswith(f" {row.state}")


# Psych-DS
def check_psych_ds(folder: Path, counts: dict[str, int]) -> None:
    """The Psych-DS 1.5.0 schema's rules: the dataset description at the root (JSON-LD,
    schema.org Dataset, its required fields), a data folder whose CSVs are named by keywords,
    and each datafile's compiled metadata (the description, then its sidecar) listing
    exactly its columns."""
    rules = PSYCH_DS
    description = json.loads((folder / DESCRIPTION_FILE).read_text(encoding="utf-8"))
    assert description["@context"] in rules["contexts"]
    assert description["@type"] in rules["dataset_types"]
    required = [k for k, v in rules["compiled_metadata"]["fields"].items() if v == "required"]
    assert required == ["name", "description", "variableMeasured"]
    for key in required:
        assert description.get(key), key
    assert (folder / "data").is_dir()
    regex = re.compile(rules["datafile"]["fileRegex"])
    datafiles = sorted((folder / "data").glob("*.csv"))
    assert len(datafiles) == len(counts)
    found_counts = {}
    every_column: set[str] = set()
    for path in datafiles:
        assert regex.fullmatch(path.name), path.name
        keys = [pair.split("-")[0] for pair in path.name.removesuffix("_data.csv").split("_")]
        assert set(keys) <= set(rules["keywords"]), path.name
        compiled = {**description}
        sidecar = path.with_suffix(".json")
        if sidecar.exists():
            compiled.update(json.loads(sidecar.read_text(encoding="utf-8")))
        measured = [v["name"] if isinstance(v, dict) else v for v in compiled["variableMeasured"]]
        with path.open(newline="", encoding="utf-8") as file:
            reader = csv.reader(file)
            header = next(reader)
            rows = list(reader)
        assert header and len(set(header)) == len(header), path.name  # CSVHeaderRepeated
        assert all(len(row) == len(header) for row in rows), path.name
        assert set(header) <= set(measured), path.name  # containsAllColumns
        assert set(measured) <= set(header), path.name  # columnsMatchMetadata
        every_column |= set(header)
        name = path.name.split("_description-")[1].removesuffix("_data.csv")
        found_counts[name] = len(rows)
    # VariableMissingFromCsvColumns: every variable of the description is some file's column.
    assert {v["name"] for v in description["variableMeasured"]} == every_column
    camel = {re.sub(r"_(\w)", lambda m: m.group(1).upper(), name): n for name, n in counts.items()}
    assert found_counts == camel


def test_the_psych_ds_folder_passes_the_schema_rules(release: Path) -> None:
    check_psych_ds(release / "psych-ds", row_counts(release))
    description = json.loads((release / "psych-ds" / DESCRIPTION_FILE).read_text())
    measured = {v["name"]: v for v in description["variableMeasured"]}
    assert set(measured) == {column for columns in DICTIONARY.values() for column in columns}
    assert measured["seed"]["description"] == DICTIONARY["sessions"]["seed"]
    assert "In participants.csv:" in measured["status"]["description"]
    assert description["license"] == "CC-BY-4.0"
    assert (release / "psych-ds" / "README.md").exists()


def test_a_bad_dataset_table_is_refused_by_check(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = study_file(tmp_path, '\n[dataset]\nlicense = "my own licence"\nbias = "typo"\n')
    assert main(["check", str(path), "--out", str(tmp_path / "check")]) == 2
    err = capsys.readouterr().err
    assert "dataset.license" in err and "dataset.bias" in err
    assert not (tmp_path / "check").exists()


# Erasure
def test_after_an_erasure_every_format_validates_without_the_participant(
    study: str, tmp_path: Path
) -> None:
    copy = tmp_path / "copy.db"
    source = sqlite3.connect(study.removeprefix("sqlite:///"))
    target = sqlite3.connect(copy)
    source.backup(target)
    source.close()
    target.close()
    url = f"sqlite:///{copy}"
    before = export_all(url, tmp_path / "before", study_file(tmp_path))
    erased = csv_rows(before / "participants.csv")[1]
    assert main(["erase", erased["participant_id"], "--database-url", url, "--yes"]) == 0
    out = export_all(url, tmp_path / "after", study_file(tmp_path))
    counts = row_counts(out)
    check_data_package(out)
    check_croissant(out)
    check_parquet(out, counts)
    check_psych_ds(out / "psych-ds", counts)
    assert counts["erasures"] == 1 and counts["participants"] == 1
    who = int(erased["participant_id"])
    pseudonyms = {erased["platform_participant_id"], erased["platform_submission_id"]}
    for path in out.rglob("*"):
        if path.is_dir() or "erasures" in path.name:
            continue
        if path.suffix == ".parquet":
            frame = pd.read_parquet(path)
            text = frame.to_csv(index=False)
            if "participant_id" in frame.columns:
                assert who not in set(frame["participant_id"]), path
        else:
            text = path.read_text(encoding="utf-8")
            if path.suffix == ".csv" and "participant_id" in text.splitlines()[0].split(","):
                ids = {row["participant_id"] for row in csv_rows(path)}
                assert str(who) not in ids, path
        for pseudonym in pseudonyms:
            assert pseudonym not in text, (path, pseudonym)
    assert (
        "1 erased on request"
        in json.loads((out / "croissant.json").read_text())["rai:dataCollection"]
    )
    assert {key.file for key in FOREIGN_KEYS} <= set(FILES)


def test_the_command_offers_every_release_format() -> None:
    from server.app.export.release import RELEASE_FORMATS
    from server.commands.export import FORMATS, RELEASE

    assert RELEASE == RELEASE_FORMATS and set(RELEASE) < set(FORMATS)
