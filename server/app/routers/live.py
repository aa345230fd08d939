"""Watching the study while it runs (``server.app.live``): the live funnel, the agents' learning
curves so far and the one-way mirror onto a participant's current session, each as JSON (one
snapshot now) and as server-sent events (``text/event-stream``: the latest snapshot at once,
then each change), behind the admin token; and the dashboard's pages that show them.

Every watcher of a view gets the same snapshot, computed once per interval however many watch
(``live.broadcast``); the mirror only reads, so the participant can notice nothing. The streams
are left out of the OpenAPI schema: they never end, and are no JSON a client could check.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from typing import Any

from fastapi import APIRouter, Request, Response
from fastapi.responses import HTMLResponse, StreamingResponse

from server.app.deps import AdminDep, RowId, StateDep, is_admin
from server.app.errors import ApiError
from server.app.live import curves, funnel, mirror
from server.app.live.broadcast import Broadcast
from server.app.live.views import LiveViews
from server.app.routers.common import login_redirect, templates
from server.app.storage.models import utcnow
from server.names import LEARNER_REGISTRY

router = APIRouter(prefix="/api/admin/live", tags=["admin"], dependencies=[AdminDep])
pages = APIRouter(tags=["dashboard"], include_in_schema=False)

# No cache or proxy may keep or buffer a stream (nginx buffers unless told not to).
STREAM_HEADERS = {"Cache-Control": "no-store", "X-Accel-Buffering": "no"}


def live_views(request: Request) -> LiveViews:
    views: LiveViews = request.app.state.live
    return views


def stream(broadcast: Broadcast, event: str) -> StreamingResponse:
    async def events() -> AsyncIterator[str]:
        yield "retry: 2000\n\n"
        async for message in broadcast.watch(event):
            yield message

    return StreamingResponse(events(), media_type="text/event-stream", headers=STREAM_HEADERS)


@router.get("/funnel")
async def read_funnel(state: StateDep) -> dict[str, Any]:
    """Participants at each stage now, those in progress with their stage, how long they have
    been there, idle or a failed check, and the learner updates pending."""

    def read() -> dict[str, Any]:
        with state.db.connect() as c:
            return funnel.funnel(c, utcnow())

    return await state.run_db(read)


@router.get("/funnel/stream", response_class=StreamingResponse, include_in_schema=False)
async def stream_funnel(request: Request) -> StreamingResponse:
    """The funnel as server-sent events (``event: funnel``), with the update manager's queue."""
    return stream(live_views(request).funnel, "funnel")


@router.get("/curves")
async def read_curves(state: StateDep) -> dict[str, Any]:
    """Per environment and learner: mean normalised return against episodes so far (with its
    standard error) and the share of sessions past each threshold."""

    def read() -> dict[str, Any]:
        with state.db.connect() as c:
            return curves.live_curves(c)

    return await state.run_db(read)


@router.get("/curves/stream", response_class=StreamingResponse, include_in_schema=False)
async def stream_curves(request: Request) -> StreamingResponse:
    """The curves as server-sent events (``event: curves``)."""
    return stream(live_views(request).curves, "curves")


def _exists(state: Any, participant_id: int) -> dict[str, Any]:
    with state.db.connect() as c:
        view = mirror.mirror_view(c, state.study, participant_id)
    if view is None:
        raise ApiError(404, f"no participant {participant_id}")
    return view


@router.get("/participants/{participant_id}/mirror")
async def read_mirror(participant_id: RowId, state: StateDep) -> dict[str, Any]:
    """What the participant sees now (read only; no identifier in it)."""
    return await state.run_db(lambda: _exists(state, participant_id))


@router.get(
    "/participants/{participant_id}/mirror/stream",
    response_class=StreamingResponse,
    include_in_schema=False,
)
async def stream_mirror(
    participant_id: RowId, request: Request, state: StateDep
) -> StreamingResponse:
    """What the participant sees, as server-sent events (``event: mirror``) at each change; it
    follows them from agent to agent."""
    await state.run_db(lambda: _exists(state, participant_id))
    views = live_views(request)
    views.forget_unwatched()
    return stream(views.mirror(participant_id), "mirror")


@pages.get("/dashboard/live", response_class=HTMLResponse)
def live_page(request: Request, state: StateDep) -> Response:
    if not is_admin(request, state):
        return login_redirect("/dashboard/live")
    return templates.TemplateResponse(
        request,
        "live.html",
        {
            "study": state.study.public(),
            "stage_labels": funnel.STAGES,
            "learner_colours": {
                name: {"colour": info.colour, "display": info.display}
                for name, info in LEARNER_REGISTRY.items()
            },
        },
        headers={"Cache-Control": "no-store"},
    )


@pages.get("/dashboard/live/participants/{participant_id}", response_class=HTMLResponse)
def mirror_page(participant_id: RowId, request: Request, state: StateDep) -> Response:
    path = f"/dashboard/live/participants/{participant_id}"
    if not is_admin(request, state):
        return login_redirect(path)
    return templates.TemplateResponse(
        request,
        "mirror.html",
        {"study": state.study.public(), "participant_id": participant_id},
        headers={"Cache-Control": "no-store"},
    )
