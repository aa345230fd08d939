"""``bam-study serve``: run the study server (settings from BAM_* environment variables)."""

from __future__ import annotations

import argparse
import sys


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (127.0.0.1)")
    parser.add_argument("--port", type=int, default=8000, help="port (8000)")
    parser.add_argument("--database-url", help="overrides BAM_DATABASE_URL")
    parser.add_argument(
        "--log-level", default="info", choices=("debug", "info", "warning", "error")
    )
    parser.add_argument("--access-log", action="store_true", help="log every request")


def run(args: argparse.Namespace) -> int:
    import logging

    import uvicorn
    from pydantic import ValidationError

    from server.app.admin_auth import weak_admin_token
    from server.app.config import StudyConfigError, load_study_config
    from server.app.db import Database, SchemaError, prepare_schema
    from server.app.main import create_app
    from server.app.settings import Settings

    try:
        settings = Settings(**({"database_url": args.database_url} if args.database_url else {}))
        study = load_study_config(settings.study_config)
    except (ValidationError, StudyConfigError) as error:
        print(f"bam-study serve: {error}", file=sys.stderr)
        return 2
    weak = weak_admin_token(settings)
    if weak is not None:
        print(f"bam-study serve: {weak}", file=sys.stderr)
        return 2
    db = Database.from_url(
        settings.database_url,
        busy_timeout_ms=settings.sqlite_busy_timeout_ms,
        synchronous=settings.sqlite_synchronous,
    )
    try:
        print(prepare_schema(db.engine), file=sys.stderr)
    except SchemaError as error:
        print(f"bam-study serve: {error}", file=sys.stderr)
        db.dispose()
        return 1
    except Exception as error:  # the database cannot be reached
        print(f"bam-study serve: cannot use the database: {error}", file=sys.stderr)
        db.dispose()
        return 1
    logging.basicConfig(level=args.log_level.upper(), format="%(levelname)s %(name)s: %(message)s")
    app = create_app(settings, study, db=db)
    uvicorn.run(
        app,
        host=args.host,
        port=args.port,
        log_level=args.log_level,
        access_log=args.access_log,
        timeout_graceful_shutdown=5,
    )
    db.dispose()
    return 0
