"""The study server's FastAPI application (``create_app``)."""

from __future__ import annotations

import asyncio
import json
import logging
import math
import threading
from collections.abc import AsyncIterator, Callable
from concurrent.futures import Executor
from contextlib import asynccontextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles
from fastapi.telemetry import TelemetryConfig
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from server.app.errors import ApiError, InvalidInput, TurnedAway
from server.app.live.views import LiveViews
from server.app.participants import statuses
from server.app.rights.scrub import scrub
from server.app.routers import (
    admin,
    arrivals,
    dashboard,
    live,
    mturk,
    pages,
    participant,
    prolific,
    sessions,
    study,
)
from server.app.schemas import ERROR_RESPONSES
from server.app.settings import Settings, get_settings
from server.app.state import ServerState
from server.app.storage.database_cpu import postgres_cpu_reader
from server.app.storage.db import Database, SchemaError, current_revision, head_revision
from server.app.storage.periodic import once_per_period
from server.app.study_file import StudyConfig, load_study_config
from server.app.updates.capacity import reference_jobs
from server.app.updates.manager import UpdateManager

if TYPE_CHECKING:
    from server.app.updates.cluster import UpdateCluster

log = logging.getLogger("bam_study")
STATIC_DIR = Path(__file__).resolve().parents[1] / "static"
SWEEP_SECONDS = 60.0

# FastAPI's OpenTelemetry instrumentation, off unless BAM_OPENTELEMETRY (settings.py).
TELEMETRY_OFF: TelemetryConfig = {"tracing": False, "metrics": False, "logs": False}


# The most bytes JSON spends on one byte of text: "\u0001" for a control character.
ESCAPE_EXPANSION = 6


class BodyLimit:
    """413 for request bodies over ``limit`` bytes (or the path's own limit in ``larger``),
    declared or streamed: the body is read (it is small) before the app sees it. A JSON body is
    measured by the text it holds (written compactly in UTF-8), so that \\u escapes (Python's
    json module writes every character past ASCII as one or two) do not make a valid request
    too large; no more than ``ESCAPE_EXPANSION`` times the limit is read."""

    def __init__(self, app: ASGIApp, limit: int, larger: dict[str, int] | None = None) -> None:
        self.app = app
        self.default_limit = limit
        self.larger = larger or {}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = max(self.default_limit, self.larger.get(scope["path"], 0))
        ceiling = ESCAPE_EXPANSION * limit
        for name, value in scope["headers"]:
            if name == b"content-length" and (not value.isdigit() or int(value) > ceiling):
                await self._refuse(scope, send, limit)
                return
        body = bytearray()
        while True:
            message = await receive()
            if message["type"] != "http.request":
                break
            body += message.get("body", b"")
            if len(body) > ceiling:
                await self._refuse(scope, send, limit)
                return
            if not message.get("more_body", False):
                message = {"type": "http.request", "body": bytes(body), "more_body": False}
                break
        if len(body) > limit and text_size(bytes(body)) > limit:
            await self._refuse(scope, send, limit)
            return
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return message
            return await receive()

        await self.app(scope, replay, send)

    async def _refuse(self, scope: Scope, send: Send, limit: int) -> None:
        response = JSONResponse(
            {"detail": f"request body too large (more than {limit} bytes)"}, status_code=413
        )
        await response(scope, _no_receive, send)


def text_size(body: bytes) -> int:
    """The bytes of the text a JSON body holds, written compactly in UTF-8 (a lone surrogate as
    its three bytes); another body's own size."""
    try:
        value = json.loads(body)
        text = json.dumps(value, ensure_ascii=False, separators=(",", ":"))
    except (ValueError, RecursionError):
        return len(body)
    return len(text.encode("utf-8", "surrogatepass"))


async def _no_receive() -> Message:
    return {"type": "http.disconnect"}


# Teaching's requests come first: the router tries the routers in this order, and they are
# most of a study's requests.
ROUTERS = (
    sessions.router,
    study.router,
    arrivals.router,
    participant.router,
    admin.router,
    live.router,
    pages.router,
    dashboard.pages,
    live.pages,
    mturk.router,
    prolific.router,
)


def _handle_errors(app: FastAPI) -> None:
    """The app's answers to refusals: an ``ApiError`` as its status and message, a request
    FastAPI finds invalid as FastAPI's own 422, both written as strict JSON."""

    @app.exception_handler(ApiError)
    async def api_error(request: Request, error: ApiError) -> JSONResponse:
        content: dict[str, Any] = {"detail": error.message}
        if error.status == 422:
            # Every 422 in the shape of FastAPI's own (HTTPValidationError): a list of problems.
            loc = list(error.loc) if isinstance(error, InvalidInput) else []
            content = {"detail": [{"type": "value_error", "loc": loc, "msg": error.message}]}
        if isinstance(error, TurnedAway):
            content["turned_away"] = True
        # The message may quote the request (a question id), which may hold a lone surrogate.
        return JSONResponse(_writable(content), status_code=error.status, headers=error.headers)

    @app.exception_handler(RequestValidationError)
    async def invalid_request(request: Request, error: RequestValidationError) -> JSONResponse:
        # FastAPI's own handler echoes the input as it was parsed, which JSON cannot always
        # write (NaN, Infinity, a lone surrogate): the echo is made writable here.
        return JSONResponse({"detail": _writable(list(error.errors()))}, status_code=422)


async def _update_manager(
    state: ServerState,
    executor: Executor | None,
    updates_cluster: UpdateCluster | None,
    measure_capacity: bool,
    server_share: Callable[[threading.Event], float] | None,
) -> UpdateManager:
    """The server's update manager, as ``create_app`` describes its arguments."""
    return UpdateManager(
        state.db,
        state.policies,
        state.study.settings_of,
        workers=state.settings.update_workers,
        niceness=state.settings.update_worker_niceness,
        threads=state.settings.update_threads,
        executor=executor,
        cluster=updates_cluster,
        update_interval_seconds=state.settings.update_interval_seconds,
        reference_jobs=(
            reference_jobs(state.study.pairs(), state.study.settings_of)
            if measure_capacity
            else None
        ),
        server_share=server_share if measure_capacity else None,
        database_cpu=(
            await asyncio.to_thread(postgres_cpu_reader, state.db.engine)
            if updates_cluster is None
            else None
        ),
        lease_seconds=state.settings.update_lease_seconds,
    )


def create_app(
    settings: Settings | None = None,
    study_config: StudyConfig | None = None,
    db: Database | None = None,
    executor: Executor | None = None,
    cluster: UpdateCluster | None = None,
    measure_capacity: bool = False,
    server_share: Callable[[threading.Event], float] | None = None,
) -> FastAPI:
    """The app for one study database. ``executor`` runs learner updates (a process pool of
    ``BAM_UPDATE_WORKERS`` is made when None), or ``cluster``, a Dask cluster's client (one is
    connected to ``BAM_UPDATE_SCHEDULER`` when that is set and ``cluster`` is None); the schema must be up to date (``bam-study db
    upgrade``, which ``bam-study serve`` runs itself on SQLite). ``measure_capacity``: time
    the study's reference updates once the update processes are warm
    (``server.app.updates.capacity``; ``serve`` does); ``server_share``: then time the
    server's own CPU seconds per update (``server.commands.server_share``), which the
    capacity counts where the update processes share the server's cores."""
    settings = settings or get_settings()
    study_config = study_config or load_study_config(settings.study_config)
    study_config.register_environments()
    own_db = db is None
    if db is None:
        db = Database.from_url(
            settings.database_url,
            busy_timeout_ms=settings.sqlite_busy_timeout_ms,
            synchronous=settings.sqlite_synchronous,
        )
    state = ServerState(db=db, study=study_config, settings=settings)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        head, current = head_revision(), current_revision(db.engine)
        if current != head:
            raise SchemaError(
                f"the database schema is at {current or 'none'}, this server needs {head}: "
                "run `bam-study db upgrade`"
            )
        updates_cluster, own_cluster = cluster, False
        if updates_cluster is None and settings.update_scheduler:
            from server.app.updates.cluster import UpdateCluster

            updates_cluster = await asyncio.to_thread(
                UpdateCluster.connect, settings.update_scheduler
            )
            own_cluster = True
        manager = await _update_manager(
            state, executor, updates_cluster, measure_capacity, server_share
        )
        state.updates = manager
        await manager.start()
        sweeper = asyncio.ensure_future(_sweep_forever(state, manager.server))
        follower = asyncio.ensure_future(prolific.follow_capacity_forever(state, manager.server))
        try:
            yield
        finally:
            sweeper.cancel()
            follower.cancel()
            await asyncio.gather(sweeper, follower, return_exceptions=True)
            await app.state.live.stop()
            await manager.stop()
            if own_cluster:
                assert updates_cluster is not None
                await asyncio.to_thread(updates_cluster.close)
            state.updates = None
            if own_db:
                db.dispose()

    app = FastAPI(
        title="BAM Study",
        summary="Participants teach learning agents in grid worlds; every event is stored.",
        lifespan=lifespan,
        responses=ERROR_RESPONSES,
        telemetry=None if settings.opentelemetry else TELEMETRY_OFF,
    )
    app.state.server = state
    app.state.live = LiveViews(state)  # the dashboard's live views (``routers.live``)
    # The questionnaire's answers may be longer than any other request (free text).
    answers = {"/api/participant/questionnaire": study_config.questionnaire.largest_answers_bytes()}
    app.add_middleware(BodyLimit, limit=settings.max_body_bytes, larger=answers)

    _handle_errors(app)
    for router in ROUTERS:
        app.include_router(router)
    if STATIC_DIR.is_dir():
        app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
    return app


def _writable(value: Any) -> Any:
    """``value`` with what strict JSON cannot hold written as text: non-finite numbers, lone
    surrogates (as escapes), and objects other than JSON's types."""
    if isinstance(value, str):
        return value.encode("utf-8", "backslashreplace").decode("utf-8")
    if isinstance(value, bool | int | None):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else str(value)
    if isinstance(value, dict):
        return {str(_writable(k)): _writable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_writable(v) for v in value]
    return _writable(str(value))


async def _sweep_forever(state: ServerState, server: str) -> None:
    """Mark participants idle for too long as abandoned (they continue if they come back), and
    replace platform ids past ``scrub_identifiers_after_days`` by their pseudonyms: once per
    ``SWEEP_SECONDS`` on the whole deployment, by whichever server comes first
    (``once_per_period``)."""

    def time_outs() -> None:
        marked = statuses.mark_abandoned(state.db, state.settings)
        if marked:
            log.info("%d participant(s) marked abandoned", marked)

    def scrubbing() -> None:
        secret = state.settings.secret.get_secret_value() if state.settings.secret else None
        scrubbed = scrub(state.db, secret, state.study.scrub_identifiers_after_days)
        if scrubbed:
            log.info("%d participant(s)' platform ids replaced by pseudonyms", scrubbed)

    while True:
        for job, work, failure in (
            ("time-outs", time_outs, "could not mark abandoned participants"),
            ("scrubbing", scrubbing, "could not replace expired platform ids"),
        ):
            try:
                await asyncio.to_thread(once_per_period, state.db, job, SWEEP_SECONDS, server, work)
            except Exception:
                log.exception(failure)
        await asyncio.sleep(SWEEP_SECONDS)
