"""``bam-study export``: the study's data as CSV files with a data dictionary."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--database-url", help="overrides BAM_DATABASE_URL")
    parser.add_argument("--out", required=True, type=Path, help="folder to write the CSVs into")
    parser.add_argument(
        "--no-pseudonymize",
        dest="pseudonymize",
        action="store_false",
        help="keep worker and assignment ids and completion codes as they are",
    )


def run(args: argparse.Namespace) -> int:
    from server.app import db as database
    from server.app.export import load_tables, open_study_database, write_export
    from server.app.settings import SettingsError, load_settings

    try:
        settings = load_settings({"database_url": ("--database-url", args.database_url)})
    except SettingsError as error:
        print(f"bam-study export: {error}", file=sys.stderr)
        return 2
    try:
        db = open_study_database(settings.database_url)  # read-only: never creates a database
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
        tables = load_tables(db, pseudonymize=args.pseudonymize, secret=secret)
        written = write_export(tables, args.out)
    except Exception as error:
        print(f"bam-study export: {error}", file=sys.stderr)
        return 1
    finally:
        db.dispose()
    for path in written:
        rows = tables[path.stem].shape[0] if path.stem in tables else None
        print(f"{path}" + (f"  ({rows} rows)" if rows is not None else ""))
    return 0
