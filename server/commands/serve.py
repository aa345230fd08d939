"""``bam-study serve``: run the study server (settings from BAM_* environment variables)."""

from __future__ import annotations

import argparse
import functools
import socket
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import uvicorn
    from fastapi import FastAPI

    from server.app.settings import Settings
    from server.app.study_file import StudyConfig

PROG = "bam-study serve"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (127.0.0.1)")
    parser.add_argument("--port", type=int, default=8000, help="port (8000)")
    parser.add_argument("--database-url", help="overrides BAM_DATABASE_URL")
    parser.add_argument(
        "--lab",
        action="store_true",
        help="also let in participants who open /study with no platform parameters (a lab "
        "study: the page gives them a completion code), whatever the study file says",
    )
    parser.add_argument(
        "--update-scheduler",
        metavar="ADDRESS",
        help="run the learner updates on the Dask cluster of this scheduler (tcp://host:8786); "
        "overrides BAM_UPDATE_SCHEDULER",
    )
    parser.add_argument(
        "--log-level", default="info", choices=("debug", "info", "warning", "error")
    )
    parser.add_argument(
        "--access-log",
        action="store_true",
        help="log every request (participants' platform ids as their pseudonyms)",
    )


def listen(host: str, port: int) -> socket.socket:
    """The server's listening socket, bound now, so that a port in use fails before anything
    starts (uvicorn would first start the app and its update processes). Raises OSError."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, port))
        sock.listen(2048)
    except OSError:
        sock.close()
        raise
    sock.set_inheritable(True)
    return sock


def run(args: argparse.Namespace) -> int:
    from server.app.settings import SettingsError, load_settings
    from server.app.study_file import StudyConfigError, load_study_config

    try:
        settings = load_settings(
            {
                "database_url": ("--database-url", args.database_url),
                "update_scheduler": ("--update-scheduler", args.update_scheduler),
            }
        )
    except SettingsError as error:
        print(f"{PROG}: {error}", file=sys.stderr)
        return 2
    try:
        study = load_study_config(settings.study_config)
    except StudyConfigError as error:
        problems = "; ".join(line.strip() for line in str(error).splitlines() if line.strip())
        where = "BAM_STUDY_CONFIG: " if settings.study_config else ""
        print(f"{PROG}: {where}{problems.replace(':;', ':')}", file=sys.stderr)
        return 2
    if args.lab:
        study = study.model_copy(update={"allow_anonymous": True})
    from server.app.admin_auth import weak_admin_token

    weak = weak_admin_token(settings)
    if weak is not None:
        print(f"{PROG}: {weak}", file=sys.stderr)
        return 2
    if not 1 <= args.port <= 65535:
        print(f"{PROG}: --port must be a number from 1 to 65535, got {args.port}", file=sys.stderr)
        return 2
    from server.app.storage.db import SecondServer, single_server_lock

    try:
        lock = single_server_lock(settings.database_url)
    except Exception:  # a URL SQLAlchemy cannot read: the database's own message follows
        lock = None
    if lock is not None:
        try:
            lock.acquire()
        except SecondServer as error:
            print(f"{PROG}: {error}", file=sys.stderr)
            return 1
        except OSError as error:
            print(f"{PROG}: cannot lock the SQLite database: {error}", file=sys.stderr)
            return 1
    try:
        return _serve(args, settings, study, lock is not None)
    finally:
        if lock is not None:
            lock.release()


def _serve(args: argparse.Namespace, settings: Settings, study: StudyConfig, single: bool) -> int:
    """``run`` once the settings are read and the SQLite file (``single``) is this server's."""
    import errno

    from server.app.admin_auth import admin_token

    try:
        sock = listen(args.host, args.port)
    except OSError as error:
        reason = error.strerror or str(error)
        if error.errno == errno.EADDRINUSE:
            reason = "the address is already in use (another server?); choose another --port"
        print(f"{PROG}: cannot listen on {args.host}:{args.port}: {reason}", file=sys.stderr)
        return 1
    # The server's own modules (the learners among them) are imported once the port is ours.
    import logging

    import uvicorn

    from server.app.main import create_app
    from server.app.rights.log_ids import keep_ids_out_of_logs
    from server.app.rights.pseudonyms import database_secret
    from server.app.storage.db import Database, SchemaError, prepare_schema

    db = Database.from_url(
        settings.database_url,
        busy_timeout_ms=settings.sqlite_busy_timeout_ms,
        synchronous=settings.sqlite_synchronous,
    )
    try:
        print(prepare_schema(db.engine), file=sys.stderr)
    except SchemaError as error:
        print(f"{PROG}: {error}", file=sys.stderr)
        db.dispose()
        sock.close()
        return 1
    except Exception as error:  # the database cannot be reached
        print(f"{PROG}: cannot use the database: {error}", file=sys.stderr)
        db.dispose()
        sock.close()
        return 1
    cluster = None
    if settings.update_scheduler:
        from server.app.updates.cluster import UpdateCluster
        from server.dask_client import SchedulerError

        try:
            cluster = UpdateCluster.connect(settings.update_scheduler)
        except SchedulerError as error:
            print(f"{PROG}: {error}", file=sys.stderr)
            db.dispose()
            sock.close()
            return 1
        print(f"Learner updates run on the Dask cluster at {cluster.address}.", file=sys.stderr)
    address = listening_address(args.host, args.port)
    for line in startup_notes(address, admin_token(settings) is not None, study):
        print(line, file=sys.stderr)
    logging.basicConfig(level=args.log_level.upper(), format="%(levelname)s %(name)s: %(message)s")
    from server.commands.server_share import measure_server_share

    app = create_app(
        settings,
        study,
        db=db,
        cluster=cluster,
        measure_capacity=True,
        server_share=functools.partial(measure_server_share, settings, study),
    )
    server = uvicorn.Server(
        server_config(app, settings, args.host, args.port, args.log_level, args.access_log)
    )
    # After uvicorn's Config, which sets up its loggers.
    keep_ids_out_of_logs(
        settings.secret.get_secret_value() if settings.secret else database_secret(db)
    )
    try:
        server.run(sockets=[sock])
    finally:
        sock.close()
        db.dispose()
        if cluster is not None:
            cluster.close()
    return 0


def server_config(
    app: FastAPI,
    settings: Settings,
    host: str,
    port: int,
    log_level: str = "info",
    access_log: bool = False,
) -> uvicorn.Config:
    """How uvicorn serves the app. X-Forwarded-* headers are believed only from the proxies
    ``BAM_FORWARDED_ALLOW_IPS`` names (uvicorn's own default believes 127.0.0.1, so a client
    on the server's host could pose as any address and escape the sign-in limit)."""
    import uvicorn

    proxies = settings.forwarded_allow_ips
    return uvicorn.Config(
        app,
        host=host,
        port=port,
        log_level=log_level,
        access_log=access_log,
        timeout_graceful_shutdown=5,
        proxy_headers=bool(proxies),
        forwarded_allow_ips=proxies or [],
    )


def listening_address(host: str, port: int) -> str:
    """The server's base URL as the console shows it."""
    return f"http://[{host}]:{port}" if ":" in host else f"http://{host}:{port}"


def startup_notes(address: str, admin_token: bool, study: StudyConfig) -> list[str]:
    """What the console says before the server starts: where it listens, who may enter, and
    whether the dashboard is open."""
    mode = study.completion.mode
    lines = [f"Serving at {address} (the study at /study)."]
    if mode == "lab" or study.allow_anonymous:
        lines.append("Lab participants enter at /study with no parameters.")
    else:
        where = "Mechanical Turk" if mode == "mturk" else "Prolific"
        lines.append(
            f"This study runs on {where}: /study turns away visitors without its parameters "
            "(serve --lab lets them in)."
        )
    if admin_token:
        lines.append(f"The dashboard is open at {address}/dashboard: sign in with BAM_ADMIN_TOKEN.")
    else:
        lines.append(
            "BAM_ADMIN_TOKEN is not set: the dashboard (/dashboard), the MTurk replica (/mturk) "
            "and the admin API are locked. Set it and restart to use them."
        )
    return lines
