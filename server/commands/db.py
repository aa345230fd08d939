"""``bam-study db``: create or upgrade the database schema (Alembic migrations); ``scrub``
replaces participants' platform ids by their pseudonyms (``server.app.rights.scrub``)."""

from __future__ import annotations

import argparse
import sys
from typing import Any


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "action",
        choices=("upgrade", "current", "check", "scrub"),
        help="upgrade: apply the migrations; current: show the revision; "
        "check: exit 1 unless the schema is up to date; scrub: replace worker, assignment and "
        "Prolific ids and completion codes by their pseudonyms (every participant, or those "
        "idle for --older-than-days)",
    )
    parser.add_argument(
        "--older-than-days",
        type=float,
        help="scrub: only participants whose last request is older than this (default: all)",
    )
    parser.add_argument("--database-url", help="overrides BAM_DATABASE_URL")
    parser.add_argument("--revision", default="head", help="upgrade to this revision (head)")


def run(args: argparse.Namespace) -> int:
    from server.app.settings import SettingsError, load_settings
    from server.app.storage import db as database

    try:
        settings = load_settings({"database_url": ("--database-url", args.database_url)})
    except SettingsError as error:
        print(f"bam-study db: {error}", file=sys.stderr)
        return 2
    engine = database.create_db_engine(
        settings.database_url, busy_timeout_ms=settings.sqlite_busy_timeout_ms
    )
    url = engine.url.render_as_string(hide_password=True)
    try:
        head = database.head_revision()
        current = database.current_revision(engine)
        if args.action == "current":
            print(f"{url}: revision {current or 'none (empty)'}; latest {head}")
            return 0
        if args.action == "check":
            if current == head:
                print(f"{url}: up to date ({head})")
                return 0
            print(f"{url}: at {current or 'none'}, needs {head}: run `bam-study db upgrade`")
            return 1
        if args.action == "scrub":
            return _scrub(engine, settings, url, current, head, args.older_than_days)
        database.upgrade(engine, args.revision)
        print(
            f"{url}: upgraded from {current or 'none (empty)'} to {database.current_revision(engine)}"
        )
        return 0
    except Exception as error:
        print(f"bam-study db: {error}", file=sys.stderr)
        return 1
    finally:
        engine.dispose()


def _scrub(
    engine: Any, settings: Any, url: str, current: str | None, head: str, days: float | None
) -> int:
    from server.app.rights.scrub import scrub
    from server.app.storage.db import Database

    if current != head:
        print(
            f"bam-study db: {url} is at {current or 'none'}, needs {head}: run `bam-study db upgrade`",
            file=sys.stderr,
        )
        return 1
    if days is not None and not days >= 0:
        print("bam-study db: --older-than-days must be 0 or more", file=sys.stderr)
        return 2
    secret = settings.secret.get_secret_value() if settings.secret else None
    scrubbed = scrub(Database(engine), secret, days)
    print(f"{url}: {scrubbed} participant(s) scrubbed (platform ids replaced by pseudonyms)")
    return 0
