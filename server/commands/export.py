"""``bam-study export``: the study's data as CSV files with a data dictionary, as Minari
datasets (one per environment) for offline and imitation learning, or as a release in the
standards venues ask for (``server.app.export.release``): Croissant with its RAI fields, a
Frictionless data package, a Psych-DS folder, Parquet with a Hugging Face dataset card, or
all of them (``all``: beside the CSVs, the Psych-DS and Hugging Face folders under ``--out``)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

RELEASE = ("croissant", "datapackage", "psych-ds", "parquet")
FORMATS = ("csv", "minari", *RELEASE, "all")


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--database-url", help="overrides BAM_DATABASE_URL")
    parser.add_argument(
        "--out",
        required=True,
        type=Path,
        help="folder to write into (minari: a new or empty folder, the MINARI_DATASETS_PATH "
        "to read the datasets from)",
    )
    parser.add_argument(
        "--format",
        choices=FORMATS,
        default="csv",
        help="csv (default): the tables and data_dictionary.csv; minari: one Minari dataset "
        "per environment with the participants' episodes; croissant or datapackage: the CSVs "
        "with croissant.json or datapackage.json; psych-ds: a Psych-DS folder; parquet: "
        "Parquet files with a Hugging Face dataset card; all: the CSVs, croissant.json and "
        "datapackage.json, and the psych-ds/ and hugging-face/ folders",
    )
    parser.add_argument(
        "--no-pseudonymize",
        dest="pseudonymize",
        action="store_false",
        help="keep worker and assignment ids and completion codes as they are",
    )
    parser.add_argument(
        "--include-excluded",
        action="store_true",
        help="minari: keep the episodes of participants the experimenter excluded",
    )
    parser.add_argument(
        "--study",
        type=Path,
        help="the study file (default: BAM_STUDY_CONFIG, else the paper's study): the export "
        "knows its own environments from it, minari names it in the datasets' metadata, and "
        "the release formats read its [dataset] table, consent and payment",
    )


def run(args: argparse.Namespace) -> int:
    from server.app.export.files import write_export
    from server.app.export.tables import export_tables
    from server.app.settings import SettingsError, load_settings
    from server.app.storage import db as database
    from server.app.study_file import DEFAULT_STUDY_CONFIG
    from server.commands.studies import StudyEnvironmentsError, register_study
    from server.rl.datasets import DatasetError, check_out_folder

    try:
        settings = load_settings({"database_url": ("--database-url", args.database_url)})
    except SettingsError as error:
        print(f"bam-study export: {error}", file=sys.stderr)
        return 2
    minari = args.format == "minari"
    if not minari and args.include_excluded:
        print(
            "bam-study export: --include-excluded applies to --format minari only "
            "(the CSVs mark exclusions in participants.csv)",
            file=sys.stderr,
        )
        return 2
    study_file = args.study or settings.study_config
    if study_file is not None:
        try:
            # The study's own environments: the episodes' tasks and the quality of the
            # actions are read from them.
            register_study(study_file)
        except StudyEnvironmentsError as error:
            print(f"bam-study export: {error}", file=sys.stderr)
            return 1
    if minari:
        try:
            check_out_folder(args.out)  # before any work: an older export stays as it is
        except DatasetError as error:
            print(f"bam-study export: {error}", file=sys.stderr)
            return 1
    try:
        # Read-only: never creates a database.
        db = database.open_study_database(settings.database_url)
    except (OSError, ValueError, ImportError) as error:
        print(f"bam-study export: {error}", file=sys.stderr)
        return 1
    try:
        current, head = database.current_revision(db.engine), database.head_revision()
        if current != head:
            print(
                f"bam-study export: the database is at schema {current or 'none'}, not {head}: "
                "is this a study database? (`bam-study db upgrade` brings it up to date)",
                file=sys.stderr,
            )
            return 1
        secret = settings.secret.get_secret_value() if settings.secret else None
        if minari:
            from server.app.export.minari import StudyFile, study_datasets
            from server.rl.datasets import write_datasets

            study = StudyFile.read(study_file or DEFAULT_STUDY_CONFIG)
            datasets = study_datasets(
                db,
                study,
                pseudonymize=args.pseudonymize,
                secret=secret,
                include_excluded=args.include_excluded,
            )
            for dataset_id in write_datasets(datasets, args.out):
                dataset = next(x for x in datasets if x.id == dataset_id)
                print(f"{args.out / dataset_id}  ({len(dataset.episodes)} episodes)")
            return 0
        tables = export_tables(db, pseudonymize=args.pseudonymize, secret=secret)
        if args.format == "csv":
            written = write_export(tables, args.out)
        else:
            written = write_formats(args, tables, study_file or DEFAULT_STUDY_CONFIG)
    except Exception as error:
        hint = ""
        if study_file is None and str(error).startswith("unknown environment"):
            hint = " (the study's own environments: give its file with --study or BAM_STUDY_CONFIG)"
        print(f"bam-study export: {error}{hint}", file=sys.stderr)
        return 1
    finally:
        db.dispose()
    for path in written:
        rows = tables[path.stem].shape[0] if path.stem in tables else None
        print(f"{path}" + (f"  ({rows} rows)" if rows is not None else ""))
    return 0


def write_formats(args: argparse.Namespace, tables: dict, study_file: Path) -> list[Path]:
    """The release formats asked for, written with the study file's [dataset] table; says on
    stderr which of the authors' answers it leaves open."""
    from server.app.export.release import About, write_release
    from server.app.study_file import load_study_config

    study = load_study_config(study_file)
    about = About(tables, study, pseudonymized=args.pseudonymize)
    formats = ("csv", *RELEASE) if args.format == "all" else (args.format,)
    written = write_release(about, args.out, formats)
    unanswered = about.unanswered()
    if unanswered:
        print(
            f"bam-study export: not answered in {study_file}'s [dataset] table, and listed as "
            f"such: {', '.join(unanswered)}",
            file=sys.stderr,
        )
    return written
