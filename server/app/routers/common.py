"""What the routers share: the participant's cookie and arrival, the page templates and notices,
the dashboard's sign-in check, and the answer to a performed request. Routers import from here,
never from one another."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path
from urllib.parse import quote

from fastapi import Request, Response
from fastapi.responses import RedirectResponse
from fastapi.templating import Jinja2Templates

from server.app.admin_auth import own_origin
from server.app.participants import arrival, places, transaction, views
from server.app.schemas import ArrivalRequest, ArrivalResponse
from server.app.state import ServerState


def answer(state: ServerState, performed: transaction.Performed) -> Response:
    """The stored JSON of a performed request; its queued learner updates start now."""
    if performed.queued and state.updates is not None:
        state.updates.submit(performed.queued)
    return Response(content=performed.response, media_type="application/json")


def login_redirect(path: str) -> RedirectResponse:
    return RedirectResponse(f"/dashboard/login?next={quote(path)}", status_code=303)


TEMPLATES_DIR = Path(__file__).resolve().parents[2] / "templates"


templates = Jinja2Templates(directory=str(TEMPLATES_DIR))


def format_time(moment: datetime | None) -> str:
    """A time as "2026-11-26 10:42:07 UTC": how every time is written on the experimenter's
    pages (the dashboard's ``formatTime`` in static/js/dom.js writes the same); a time without
    a zone is UTC, as the database keeps them."""
    if moment is None:
        return ""
    if moment.tzinfo is None:
        moment = moment.replace(tzinfo=UTC)
    return moment.astimezone(UTC).strftime("%Y-%m-%d %H:%M:%S UTC")


templates.env.filters["utc"] = format_time


def notice(
    request: Request,
    title: str,
    message: str,
    status_code: int,
    form: tuple[str, str, str] | None = None,
) -> Response:
    """A page that says one thing; ``form`` (its action, name and button label) adds one
    button that posts there."""
    action, name, label = form or (None, None, None)
    return templates.TemplateResponse(
        request,
        "notice.html",
        {
            "title": title,
            "message": message,
            "form_action": action,
            "form_name": name,
            "form_label": label,
        },
        status_code=status_code,
    )


def sentence(text: str) -> str:
    """An API error's message (a clause: "the Prolific link lacks SESSION_ID") as a page's
    sentence: a capital first letter and a full stop."""
    text = text.strip()
    if not text:
        return text
    first = text.split(" ", 1)[0]
    if first.isalpha() and first.islower():  # a word, not a name such as turkSubmitTo
        text = text[0].upper() + text[1:]
    return text + ("" if text.endswith((".", "!", "?")) else ".")


def set_participant_cookie(response: Response, state: ServerState, token: str) -> None:
    settings = state.settings
    response.set_cookie(
        settings.cookie_name,
        token,
        max_age=7 * 24 * 3600,
        httponly=True,
        samesite=settings.cookie_samesite,
        secure=settings.cookie_secure,
        partitioned=settings.cookie_samesite == "none",
    )


def arrive(
    state: ServerState, body: ArrivalRequest, request: Request, response: Response
) -> ArrivalResponse:
    """Shared by the API and the page: returns the preview answer or the participant."""
    platform = arrival.classify_arrival(body, state.study, state.settings, own_origin(request))
    if platform is None:
        return ArrivalResponse(preview=True)
    cookie = request.cookies.get(state.settings.cookie_name)
    arrived = arrival.arrive(state.db, platform, cookie, state.study, places.room_for(state))
    if arrived.token is not None:
        set_participant_cookie(response, state, arrived.token)
    with state.db.connect() as c:
        view = views.participant_state(c, arrived.participant, state.study)
    return ArrivalResponse(token=arrived.token, resumed=arrived.resumed, participant=view)
