"""``bam-study erase``: erase one participant's data on their request (every row of theirs, in
one transaction, with an audit row in ``erasures``), by participant number, worker id (MTurk
workerId or Prolific PROLIFIC_PID) or its pseudonym (w_..., as in the export)."""

from __future__ import annotations

import argparse
import sys


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "who", help="participant number, worker id or worker pseudonym (w_ + 16 hex digits)"
    )
    parser.add_argument("--database-url", help="overrides BAM_DATABASE_URL")
    parser.add_argument(
        "--yes", action="store_true", help="erase without asking (needed without a terminal)"
    )


def run(args: argparse.Namespace) -> int:
    from server.app.errors import ApiError
    from server.app.rights.erasure import erase, find_participant
    from server.app.rights.pseudonyms import installation_secret, participant_pseudonyms
    from server.app.settings import SettingsError, load_settings
    from server.app.storage import db as database
    from server.app.storage.records import Record
    from server.app.storage.tables import PARTICIPANTS
    from server.app.storage.vocabulary import ErasedBy

    def fail(message: str, code: int = 1) -> int:
        print(f"bam-study erase: {message}", file=sys.stderr)
        return code

    try:
        settings = load_settings({"database_url": ("--database-url", args.database_url)})
    except SettingsError as error:
        return fail(str(error), 2)
    configured = settings.secret.get_secret_value() if settings.secret else None
    try:
        db = database.Database.from_url(settings.database_url)
    except Exception as error:
        return fail(str(error))
    try:
        current, head = database.current_revision(db.engine), database.head_revision()
        if current != head:
            return fail(
                f"the database is at schema {current or 'none'}, not {head}: "
                "run `bam-study db upgrade` first"
            )
        with db.connect() as c:
            secret = installation_secret(c, configured)
            row = find_participant(c, args.who, secret)
        worker, _ = participant_pseudonyms(Record(PARTICIPANTS, row), secret)
        described = (
            f"participant {row['id']} ({row['platform']}, status {row['status']}"
            + (f", worker {worker}" if worker else "")
            + ")"
        )
        if not args.yes:
            if not sys.stdin.isatty():
                return fail(f"would erase {described}: add --yes to erase without a terminal", 2)
            reply = input(f"Erase every record of {described}? This cannot be undone. [y/N] ")
            if reply.strip().lower() not in ("y", "yes"):
                print("nothing erased")
                return 1
        with db.transaction() as c:
            erased = erase(
                c, int(row["id"]), ErasedBy.EXPERIMENTER, installation_secret(c, configured)
            )
        db.forget_removed()
    except ApiError as error:
        return fail(error.message)
    except Exception as error:
        return fail(str(error))
    finally:
        db.dispose()
    removed = ", ".join(f"{table} {count}" for table, count in erased.rows.items() if count)
    print(f"erased {described}: {removed} (audit row {erased.erasure_id} in erasures)")
    return 0
