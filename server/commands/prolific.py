"""``bam-study prolific``: make the study on Prolific from the study file and run it there
(publish, pause, add places, see its submissions and their counts per status), through
Prolific's API (``BAM_PROLIFIC_API_URL``, ``BAM_PROLIFIC_TOKEN``) or, with ``--replica URL``,
through the Prolific replica of a running study server (its ``/prolific/api/v1``,
``BAM_ADMIN_TOKEN``).

A refusal (Prolific's 4xx) is printed as one line with Prolific's message and exit status 1;
bad arguments or a study file that cannot run on Prolific get exit status 2. No token is ever
printed.

One module for the one command: its subcommands side by side, each a short function over
the client.
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import httpx

if TYPE_CHECKING:
    from server.app.platforms.prolific import ProlificClient
    from server.app.settings import Settings
    from server.app.storage.db import Database
    from server.app.study_file import StudyConfig

STUDY_ID = re.compile(r"[0-9a-f]{24}")


class Refused(Exception):
    """What the command cannot do, said in one line (with its exit status)."""

    def __init__(self, message: str, status: int = 1) -> None:
        super().__init__(message)
        self.status = status


def study_id(text: str) -> str:
    if not STUDY_ID.fullmatch(text):
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a Prolific study id (24 hexadecimal digits)"
        )
    return text


def positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: at least 1")
    return value


def submission_status(text: str) -> str:
    """A Prolific submission status, spelt as Prolific does (AWAITING REVIEW) or as its list's
    filter does (AWAITING_REVIEW), in any case."""
    from server.app.platforms.prolific import SUBMISSION_STATUSES

    def key(name: str) -> str:
        return re.sub(r"[ _-]+", "_", name.strip().upper())

    spelt = {key(name): name for name in SUBMISSION_STATUSES}
    if key(text) not in spelt:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a Prolific submission status: one of {', '.join(spelt)}"
        )
    return spelt[key(text)]


# The events the server applies (``prolific_sync.APPLIED_EVENTS``), subscribed by ``hooks``.
HOOK_EVENTS = ("submission.status.change", "study.status.change", "study.has_high_return_rate")


def publish_time(text: str) -> str:
    """An ISO 8601 time with its time zone, in the future."""
    from datetime import UTC, datetime

    try:
        moment = datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an ISO 8601 time") from None
    if moment.tzinfo is None:
        raise argparse.ArgumentTypeError(
            f"{text!r} has no time zone: give one (2027-01-05T09:00+00:00)"
        )
    if moment <= datetime.now(UTC):
        raise argparse.ArgumentTypeError(f"{text!r} is not in the future")
    return moment.astimezone(UTC).isoformat()


def message_body(text: str) -> str:
    if not text.strip():
        raise argparse.ArgumentTypeError("the message is empty")
    return text


def configure(parser: argparse.ArgumentParser) -> None:
    actions = parser.add_subparsers(dest="action", metavar="ACTION")
    actions.required = True

    def action(name: str, help_text: str) -> argparse.ArgumentParser:
        sub = actions.add_parser(name, help=help_text, description=help_text)
        sub.add_argument(
            "--replica",
            metavar="URL",
            help="a running bam-study server: use its Prolific replica (URL/prolific/api/v1, "
            "BAM_ADMIN_TOKEN) instead of Prolific's API (BAM_PROLIFIC_TOKEN)",
        )
        return sub

    create = action(
        "create", "Make a draft study from the study file's [prolific] table; print its id."
    )
    create.add_argument("study_file", metavar="STUDY.toml", type=Path)
    create.add_argument(
        "--max-concurrent",
        type=positive,
        metavar="N",
        help="participants taking part at once (default: what the server can serve: the "
        "study file's max_active_participants, else the capacity the server measured, else "
        "the capacity measured here)",
    )
    for name, help_text in (
        (
            "publish",
            "Publish the study: participants can take part. First the workspace's currency is "
            "checked against BAM_PROLIFIC_CURRENCY, the hourly pay against Prolific's minimum, "
            "and the study's cost against the workspace's available balance.",
        ),
        ("pause", "Pause the published study: no one new takes part."),
        (
            "start",
            "Start the paused study again, or the full one (AWAITING REVIEW) to replace a "
            "returned, timed-out or rejected submission: Prolific does not reopen it by itself.",
        ),
        ("stop", "Stop the study for good (COMPLETED): no one new takes part."),
        ("status", "The study's status, places and submissions per status."),
        (
            "counts",
            "The study's submissions per Prolific status and in all, as Prolific counts them "
            "(one call: GET /studies/{id}/submissions/counts/).",
        ),
    ):
        sub = action(name, help_text)
        sub.add_argument("study_id", metavar="STUDY_ID", type=study_id)
        if name == "publish":
            sub.add_argument(
                "--force",
                action="store_true",
                help="publish even though the hourly pay is below Prolific's minimum (the "
                "balance and the currency are checked all the same)",
            )
            sub.add_argument(
                "--at",
                type=publish_time,
                metavar="WHEN",
                help="schedule the publication instead (Prolific's SCHEDULE_PUBLISH) at this "
                "time, ISO 8601 with its time zone (2027-01-05T09:00+00:00); the money is "
                "checked now",
            )
    hooks = action(
        "hooks",
        "Set up Prolific's webhooks for the study's workspace: make the workspace's signing "
        "secret (POST /hooks/secrets/, which replaces the old one) and store it in the "
        "database (BAM_DATABASE_URL), where the server's /prolific/webhook reads it; subscribe "
        f"{', '.join(HOOK_EVENTS)} at the server's address (that of the study's link) and "
        "confirm each subscription; then list the subscriptions and their deliveries.",
    )
    hooks.add_argument("study_id", metavar="STUDY_ID", type=study_id)
    hooks.add_argument(
        "--list",
        action="store_true",
        help="only list the subscriptions and their deliveries (nothing made or stored)",
    )
    hooks.add_argument("--database-url", help="overrides BAM_DATABASE_URL")
    places = action("add-places", "Raise the study's places to N (places only go up).")
    places.add_argument("study_id", metavar="STUDY_ID", type=study_id)
    places.add_argument("places", metavar="N", type=positive, help="the new number of places")
    _add_message(action)


def _add_message(action: Callable[[str, str], argparse.ArgumentParser]) -> None:
    """``bam-study prolific message`` and its arguments (``action`` makes a subcommand)."""
    message = action(
        "message",
        "Send a message through Prolific's messages API to participants of the study: those "
        "named (--to), or everyone whose submission is in a status (--status). Each recipient "
        "must be a participant of the study in the database (BAM_DATABASE_URL), where each "
        "message Prolific takes is stored (messages.csv in the export; erased with the "
        "participant).",
    )
    message.add_argument("--study", required=True, type=study_id, metavar="STUDY_ID")
    recipients = message.add_mutually_exclusive_group(required=True)
    recipients.add_argument("--to", nargs="+", metavar="PID", help="participants' PROLIFIC_PIDs")
    recipients.add_argument(
        "--status",
        type=submission_status,
        metavar="STATUS",
        help="everyone whose submission of the study has this Prolific status (AWAITING_REVIEW "
        "or 'AWAITING REVIEW', APPROVED, ACTIVE, ...), as Prolific lists them",
    )
    message.add_argument("--body", required=True, type=message_body, help="the message")
    message.add_argument("--database-url", help="overrides BAM_DATABASE_URL")


def client_for(args: argparse.Namespace, settings: Settings) -> ProlificClient:
    from server.app.platforms.prolific import ProlificClient

    if args.replica:
        token = settings.admin_token
        if token is None:
            raise Refused("--replica needs BAM_ADMIN_TOKEN, the server's admin token", 2)
        return ProlificClient(
            f"{args.replica.rstrip('/')}/prolific/api/v1", token.get_secret_value()
        )
    if settings.prolific_token is None:
        raise Refused("set BAM_PROLIFIC_TOKEN (Prolific's API token), or use --replica URL", 2)
    return ProlificClient(settings.prolific_api_url, settings.prolific_token.get_secret_value())


# How long ``create`` waits for a running server to state its capacity (its first start
# compiles the learners' kernels and times their updates: minutes), and how often it asks.
CAPACITY_WAIT_SECONDS = 1200.0
CAPACITY_ASK_SECONDS = 5.0


def server_limit(
    server: str,
    settings: Settings,
    get: Callable[..., httpx.Response] = httpx.get,
    sleep: Callable[[float], None] = time.sleep,
    clock: Callable[[], float] = time.monotonic,
) -> int | None:
    """The participants the running server serves at once (its dashboard's queue: the study
    file's limit or the capacity it measured, its own work included), waiting while it is
    still measuring; None when no server answers there."""
    if settings.admin_token is None:
        return None
    deadline = clock() + CAPACITY_WAIT_SECONDS
    said = False
    while True:
        try:
            answer = get(
                f"{server.rstrip('/')}/api/admin/queue",
                headers={"Authorization": f"Bearer {settings.admin_token.get_secret_value()}"},
                timeout=10,
            )
            answer.raise_for_status()
            limit = answer.json().get("limit")
        except (httpx.HTTPError, ValueError, AttributeError):
            return None
        if isinstance(limit, int) and limit >= 1:
            return limit
        # The server answers but has no capacity yet: what it states once measured is what
        # it admits by, so it is waited for rather than measured here.
        if clock() >= deadline:
            raise Refused(
                f"the server at {server} stated no capacity in {CAPACITY_WAIT_SECONDS:.0f} s "
                "(still measuring?): give --max-concurrent N"
            )
        if not said:
            print(
                f"waiting for the server at {server} to state its capacity (it measures it "
                "after its start)...",
                file=sys.stderr,
                flush=True,
            )
            said = True
        sleep(CAPACITY_ASK_SECONDS)


def measured_capacity(study: StudyConfig, settings: Settings) -> int:
    """The capacity of a server with these settings, its update cost measured here on the
    study's own learners and environments (``server.app.updates.capacity``)."""
    from server.app.updates.capacity import (
        measure_update_cost,
        participants_at_once,
        reference_jobs,
    )
    from server.cores import available_cores

    study.register_environments()
    seconds = measure_update_cost({"jobs": reference_jobs(study.pairs(), study.settings_of)})
    slots = min(settings.update_workers, available_cores())
    return participants_at_once(seconds, slots, settings.update_interval_seconds)


def max_concurrent(args: argparse.Namespace, study: StudyConfig, settings: Settings) -> int:
    if args.max_concurrent is not None:
        return int(args.max_concurrent)
    if study.max_active_participants is not None:
        return study.max_active_participants
    assert study.prolific is not None
    limit = server_limit(args.replica or study.prolific.public_url, settings)
    if limit is not None:
        return limit
    print(
        "measuring the server's capacity on the study's learners "
        "(give --max-concurrent N to skip)...",
        file=sys.stderr,
        flush=True,
    )
    return measured_capacity(study, settings)


def create(args: argparse.Namespace, settings: Settings) -> None:
    from server.app.platforms.prolific import draft_study
    from server.app.study_file import StudyConfigError, load_study_config

    try:
        study = load_study_config(args.study_file)
    except StudyConfigError as error:
        raise Refused(str(error), 2) from None
    if study.completion.mode != "prolific":
        raise Refused(
            f'{args.study_file}: the completion mode is "{study.completion.mode}"; a study '
            'on Prolific needs [completion] mode = "prolific" with prolific_code',
            2,
        )
    if study.prolific is None:
        raise Refused(f"{args.study_file} has no [prolific] table (docs/study-file.md)", 2)
    client = client_for(args, settings)
    try:
        limit = max_concurrent(args, study, settings)
        made = client.create_study(
            draft_study(study, limit, args.replica, participant_groups(client, study))
        )
    finally:
        client.close()
    print(made["id"])


def participant_groups(client: ProlificClient, study: StudyConfig) -> dict[str, str]:
    """The id of each participant group the ``[prolific]`` table names, by name, each made in
    the workspace where it has none of that name."""
    assert study.prolific is not None
    prolific = study.prolific
    names = [n for n in (prolific.family_group, prolific.follow_up_group, prolific.only_group) if n]
    if not names:
        return {}
    workspace = prolific.workspace_id
    if workspace is None:
        listed = client.workspaces()
        if len(listed) != 1:
            raise Refused(
                f"the account has {len(listed)} workspaces ("
                + ", ".join(f"{w.get('id')} {w.get('title', '')!r}" for w in listed)
                + "): name the study's in [prolific] workspace_id, for its participant groups",
                2,
            )
        workspace = str(listed[0]["id"])
    return {name: client.participant_group(workspace, name) for name in dict.fromkeys(names)}


def status(client: ProlificClient, study_id: str) -> None:
    from server.app.platforms.prolific import SUBMISSION_STATUSES

    study = client.get_study(study_id)
    counts = Counter(str(s.get("status")) for s in client.submissions(study_id))
    print(f"study       {study_id} ({study.get('name', '')})")
    print(f"status      {study.get('status')}")
    print(
        f"places      {study.get('places_taken', '?')} taken of {study['total_available_places']}"
    )
    print(f"submissions {sum(counts.values())}")
    for name in (*SUBMISSION_STATUSES, *sorted(set(counts) - set(SUBMISSION_STATUSES))):
        if counts[name]:
            print(f"  {name:<18} {counts[name]}")


def counts(client: ProlificClient, study_id: str) -> None:
    """Prolific's count of the study's submissions per status: each status it counts (in
    the order of its submission statuses, then any other), then the total."""
    from server.app.platforms.prolific import SUBMISSION_STATUSES

    counted = client.submission_counts(study_id)
    total = counted.pop("TOTAL", sum(counted.values()))
    known = [name for name in SUBMISSION_STATUSES if name in counted]
    print(f"study {study_id}")
    print(f"{'status':<20}{'submissions':>11}")
    for name in (*known, *sorted(set(counted) - set(known))):
        print(f"{name:<20}{counted[name]:>11}")
    print(f"{'TOTAL':<20}{total:>11}")


# Prolific's documented minimum hourly pay, in cents (researcher help: £6 / $8 an hour).
LEAST_HOURLY_REWARD = {"GBP": 600, "USD": 800}


def amount(cents: float, currency: str) -> str:
    """Cents as an amount with two decimals and the currency: 12.30 GBP."""
    whole = round(cents)
    sign = "-" if whole < 0 else ""
    return f"{sign}{abs(whole) // 100}.{abs(whole) % 100:02d} {currency}"


def publish(
    client: ProlificClient, study_id: str, settings: Settings, force: bool, at: str | None = None
) -> None:
    """Publish the study once the money is checked and shown: the workspace's currency is
    BAM_PROLIFIC_CURRENCY, the hourly pay is at least Prolific's minimum (unless ``force``),
    and the available balance covers the study's cost (its places' rewards with Prolific's
    fees and VAT, from Prolific's cost calculator)."""
    from server.app.platforms.review import ReviewRefused, ReviewUnavailable

    def go() -> None:
        if at is None:
            done = client.transition_study(study_id, "PUBLISH")
            print(f"study {study_id}: {done['status']}")
        else:
            done = client.schedule_publish(study_id, at)
            print(f"study {study_id}: {done['status']} (to publish at {at})")

    study = client.get_study(study_id)
    if study.get("status") != "UNPUBLISHED":  # Prolific refuses it: nothing to pay for
        go()
        return
    workspace = client.workspace_of(study)
    balance = client.balance(workspace)  # the workspace's currency, read once
    currency = str(balance.get("currency_code"))
    if currency != settings.prolific_currency:
        raise Refused(
            f"workspace {workspace} pays in {currency}, but BAM_PROLIFIC_CURRENCY is "
            f"{settings.prolific_currency}: the study's rewards and bonuses would be read in "
            f"the wrong currency. Set BAM_PROLIFIC_CURRENCY={currency} on the server and here "
            "(and the study file's amounts in it); the study is not published"
        )
    reward = int(study["reward"])
    places = int(study["total_available_places"])
    minutes = int(study["estimated_completion_time"])
    cost = client.study_cost(reward, places)
    available = int(balance["available_balance"])
    hourly = reward * 60 / minutes
    try:
        least = client.least_hourly_reward(workspace, currency)
        source = "Prolific's reward recommendations"
    except (ReviewRefused, ReviewUnavailable):
        least = None
    if least is None:
        least, source = LEAST_HOURLY_REWARD[currency], "Prolific's documented minimum"
    print(
        f"cost        {amount(cost, currency)} for {places} places at "
        f"{amount(reward, currency)} (with Prolific's fees and VAT)"
    )
    print(f"balance     {amount(available, currency)} available in workspace {workspace}")
    print(
        f"hourly pay  {amount(hourly, currency)} an hour for an estimated {minutes} minutes "
        f"(the least: {amount(least, currency)}, {source})",
        flush=True,
    )
    if hourly < least:
        if not force:
            raise Refused(
                f"the study pays {amount(hourly, currency)} an hour ({amount(reward, currency)} "
                f"for an estimated {minutes} minutes), below Prolific's minimum of "
                f"{amount(least, currency)} an hour: raise the reward, or give --force to "
                "publish it all the same; the study is not published"
            )
        print(
            "bam-study prolific publish: --force: publishing below Prolific's minimum hourly "
            "pay; Prolific asks for adjustment payments to studies that underpay",
            file=sys.stderr,
        )
    if available < cost:
        raise Refused(
            f"workspace {workspace} has {amount(available, currency)} available, less than the "
            f"study's cost of {amount(cost, currency)}: add at least "
            f"{amount(cost - available, currency)} to it on Prolific; the study is not published"
        )
    go()


def add_places(client: ProlificClient, study_id: str, places: int) -> None:
    study: dict[str, Any] = client.get_study(study_id)
    current = int(study["total_available_places"])
    if places <= current:
        raise Refused(
            f"places only go up: study {study_id} has {current} places, and {places} is not "
            f"more; give the new total, above {current}"
        )
    done = client.set_places(study_id, places)
    print(f"study {study_id}: {done['total_available_places']} places")


# Recipients per call: Prolific's bulk messages take a few thousand at most.
MESSAGE_BATCH = 1000


def _recipients(args: argparse.Namespace, client: ProlificClient, db: Any) -> dict[str, int]:
    """The participants to message (``--to``, or those whose submission has ``--status``),
    each PROLIFIC_PID with its participant's row; empty, and said, when there is none."""
    from sqlalchemy import select

    from server.app.storage.models import Participant

    if args.to:
        wanted = list(dict.fromkeys(args.to))
    else:
        wanted = list(
            dict.fromkeys(
                str(s["participant_id"])
                for s in client.submissions(args.study)
                if s.get("status") == args.status
            )
        )
        if not wanted:
            print(f"no submission of study {args.study} is {args.status}: nothing sent")
            return {}
    with db.read() as s:
        found = s.execute(
            select(Participant.platform_participant_id, Participant.id)
            .where(
                Participant.platform == "prolific",
                Participant.platform_study_id == args.study,
                Participant.platform_participant_id.in_(wanted),
            )
            .order_by(Participant.id)
        ).all()
    ours = {str(worker): int(number) for worker, number in found}  # the newest wins
    missing = [who for who in wanted if who not in ours]
    if missing and args.to:
        raise Refused(
            f"{', '.join(missing)}: no participant of study {args.study} in the "
            "database (an unknown PROLIFIC_PID, another study's, or one erased or "
            "scrubbed); nothing was sent"
        )
    if missing:
        print(
            f"bam-study prolific message: {len(missing)} submission(s) that are "
            f"{args.status} belong to no participant in the database (erased, or never "
            "arrived): not messaged",
            file=sys.stderr,
        )
    recipients = {who: ours[who] for who in wanted if who in ours}
    if not recipients:
        print(f"no participant of study {args.study} to message: nothing sent")
    return recipients


def message(args: argparse.Namespace, settings: Settings) -> None:
    """Send the message to the recipients through Prolific and store each one it took (one
    row per recipient in ``messages``); nothing is stored for a message it refused."""

    from server.app.storage import db as database
    from server.app.storage.models import Message, utcnow

    try:
        db = database.Database.from_url(settings.database_url)
    except Exception as error:
        raise Refused(f"cannot open the database (BAM_DATABASE_URL): {error}") from None
    try:
        current, head = database.current_revision(db.engine), database.head_revision()
        if current != head:
            raise Refused(
                f"the database is at schema {current or 'none'}, not {head}: run "
                "`bam-study db upgrade` first; nothing was sent"
            )
        client = client_for(args, settings)
        try:
            ours = _recipients(args, client, db)
            if not ours:
                return
            recipients = list(ours)
            backend = "prolific-replica" if args.replica else "prolific"
            sent = 0
            for start in range(0, len(recipients), MESSAGE_BATCH):
                batch = recipients[start : start + MESSAGE_BATCH]
                try:
                    answer = client.send_message(args.study, batch, args.body)
                except Exception:
                    if sent:
                        print(
                            f"bam-study prolific message: sent to {sent} participant(s) before "
                            "the refusal below (stored in messages)",
                            file=sys.stderr,
                        )
                    raise
                now = utcnow()
                try:
                    with db.write() as s:
                        s.add_all(
                            Message(
                                participant_id=ours[who],
                                platform_participant_id=who,
                                study_id=args.study,
                                body=args.body,
                                backend=backend,
                                sent_with="messages" if len(batch) == 1 else "messages/bulk",
                                answer_status=answer,
                                sent_at=now,
                            )
                            for who in batch
                        )
                except Exception as error:
                    raise Refused(
                        f"Prolific took the message to {sent + len(batch)} participant(s), but "
                        f"the last {len(batch)} could not be stored in messages: {error}"
                    ) from None
                sent += len(batch)
        finally:
            client.close()
    finally:
        db.dispose()
    print(
        f"sent to {sent} participant(s) of study {args.study} (Prolific answered {answer}); "
        "stored in messages"
    )


def hook_url(study: dict[str, Any]) -> str:
    """The server's webhook: ``/prolific/webhook`` at the address of the study's link (where
    participants reach the server)."""
    from urllib.parse import urlsplit

    link = urlsplit(str(study.get("external_study_url", "")))
    base = link.path.rsplit("/study", 1)[0] if "/study" in link.path else ""
    if not link.scheme or not link.netloc:
        raise Refused(f"study {study.get('id')} has no study link to find the server's address by")
    return f"{link.scheme}://{link.netloc}{base}/prolific/webhook"


def hooks(args: argparse.Namespace, settings: Settings) -> None:
    """Make the workspace's signing secret and store it, subscribe and confirm each event at
    the server's webhook (those subscribed there already are kept), and list them with their
    deliveries."""
    # The database first: a secret Prolific made and the server cannot read would fail every
    # event (the old one no longer signs).
    db = None if args.list else study_database(settings)
    client = client_for(args, settings)
    try:
        study = client.get_study(args.study_id)
        workspace = client.workspace_of(study)
        target = hook_url(study)
        if db is not None:
            secret = client.create_hook_secret(workspace)
            store_hook_secret(db, workspace, secret)
            print(
                f"workspace {workspace}: a new signing secret, stored in the database (the "
                "old one no longer signs)"
            )
            have = {
                (s.get("event_type"), s.get("target_url")) for s in client.subscriptions(workspace)
            }
            for event_type in HOOK_EVENTS:
                if (event_type, target) in have:
                    continue
                made = client.subscribe(workspace, event_type, target)
                if not made.get("is_enabled"):
                    raise Refused(f"Prolific did not confirm the subscription to {event_type}")
        listed = client.subscriptions(workspace)
        print(f"subscriptions of workspace {workspace}: {len(listed)}")
        for subscription in listed:
            events = client.hook_events(str(subscription["id"]))
            counted = Counter(str(e.get("status")) for e in events)
            tally = ", ".join(f"{n} {status}" for status, n in sorted(counted.items()))
            print(
                f"  {subscription['id']}  {subscription.get('event_type'):<28} "
                f"{subscription.get('target_url')}  deliveries: {len(events)}"
                + (f" ({tally})" if tally else "")
            )
    finally:
        client.close()
        if db is not None:
            db.dispose()


def study_database(settings: Settings) -> Database:
    """The study's database (BAM_DATABASE_URL) at the current schema, or a refusal."""
    from server.app.storage import db as database

    try:
        db = database.Database.from_url(settings.database_url)
    except Exception as error:
        raise Refused(f"cannot open the database (BAM_DATABASE_URL): {error}") from None
    current, head = database.current_revision(db.engine), database.head_revision()
    if current != head:
        db.dispose()
        raise Refused(
            f"the database is at schema {current or 'none'}, not {head}: run `bam-study db "
            "upgrade` first; nothing was sent"
        )
    return db


def store_hook_secret(db: Database, workspace: str, secret: str) -> None:
    """The workspace's secret where the server's webhook reads it (``prolific_webhook_secrets``,
    one per workspace: a new one replaces the old)."""
    from server.app.storage.models import ProlificWebhookSecret, utcnow

    with db.write() as s:
        row = s.get(ProlificWebhookSecret, workspace)
        if row is None:
            s.add(ProlificWebhookSecret(workspace_id=workspace, secret=secret, created_at=utcnow()))
        else:
            row.secret, row.created_at = secret, utcnow()


def run(args: argparse.Namespace) -> int:
    from server.app.platforms.review import ReviewRefused, ReviewUnavailable
    from server.app.settings import SettingsError, load_settings

    flags = {"database_url": ("--database-url", getattr(args, "database_url", None))}
    try:
        settings = load_settings(flags)
    except SettingsError as error:
        print(f"bam-study prolific: {error}", file=sys.stderr)
        return 2
    try:
        if args.action == "create":
            create(args, settings)
            return 0
        if args.action == "message":
            message(args, settings)
            return 0
        if args.action == "hooks":
            hooks(args, settings)
            return 0
        client = client_for(args, settings)
        try:
            if args.action == "status":
                status(client, args.study_id)
            elif args.action == "counts":
                counts(client, args.study_id)
            elif args.action == "add-places":
                add_places(client, args.study_id, args.places)
            elif args.action == "publish":
                publish(client, args.study_id, settings, args.force, args.at)
            else:
                action = args.action.upper()  # publish, pause, start, stop
                done = client.transition_study(args.study_id, action)
                print(f"study {args.study_id}: {done['status']}")
        finally:
            client.close()
    except Refused as refused:
        print(f"bam-study prolific {args.action}: {refused}", file=sys.stderr)
        return refused.status
    except (ReviewRefused, ReviewUnavailable) as error:
        print(f"bam-study prolific {args.action}: {error}", file=sys.stderr)
        return 1
    return 0
