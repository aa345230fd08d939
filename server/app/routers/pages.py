"""``GET /study``: the entry URL the platforms open (MTurk in an iframe, Prolific, a lab).

A preview gets the preview page and creates nothing; an arrival the study refuses gets a page
that says why; an arrival sets the participant's cookie and gets the study page, which then
works through the JSON API (with the participant's new token in the page, for a browser that
keeps no cookie in the platform's iframe).
"""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from fastapi.responses import HTMLResponse
from pydantic import ValidationError

from server.app.deps import StateDep
from server.app.errors import ApiError, TurnedAway
from server.app.participants import places
from server.app.platform_registry import arrival_parameters
from server.app.routers.common import arrive, notice, sentence, templates
from server.app.schemas import ArrivalRequest, ArrivalResponse
from server.app.state import ServerState
from server.app.storage.vocabulary import ParticipantStatus

router = APIRouter(tags=["pages"])


@router.get("/study", response_class=HTMLResponse)
def study_page(request: Request, state: StateDep) -> Response:
    # Platforms may append parameters of their own: only ours are read.
    ours = arrival_parameters()
    params = {k: v for k, v in request.query_params.items() if k in ours}
    try:
        body = ArrivalRequest.model_validate(params)
    except ValidationError as error:
        fields = ", ".join(
            str(e["loc"][0] if e["loc"] else e.get("ctx", {}).get("parameter"))
            for e in error.errors()
        )
        return notice(
            request, "This study link is not valid", f"Malformed parameter(s): {fields}.", 400
        )
    response = Response()
    try:
        arrival = arrive(state, body, request, response)
    except TurnedAway as refused:
        return notice(request, refused.title, refused.message, refused.status)
    except ApiError as error:
        return notice(
            request, "This study link is not valid", sentence(error.message), error.status
        )
    if arrival.preview:
        return templates.TemplateResponse(request, "preview.html", {"study": state.study.public()})
    assert arrival.participant is not None
    if arrival.participant.status == ParticipantStatus.WAITING:
        page = waiting_page(request, state, arrival.participant.participant_id, arrival.token)
    else:
        page = study_page_of(request, state, arrival)
    for key, value in response.headers.items():
        if key == "set-cookie":
            page.headers.append(key, value)
    return page


def study_page_of(request: Request, state: ServerState, arrival: ArrivalResponse) -> Response:
    # A new token is also given to the page itself, which sends it in the X-Participant-Token
    # header: in the platform's cross-site iframe the browser may keep no cookie. The page is
    # this participant's alone, so no cache may keep it.
    return templates.TemplateResponse(
        request,
        "study.html",
        {"study": state.study.public(), "participant": arrival.participant, "token": arrival.token},
        headers={"Cache-Control": "no-store"},
    )


def waiting_page(
    request: Request, state: ServerState, participant_id: int, token: str | None
) -> Response:
    """The study is full: the page that waits for a place (``places``), for this participant
    alone (with their new token, as the study page)."""
    place = places.admit(
        state.db, participant_id, places.study_limit(state), state.settings.active_minutes
    )
    return templates.TemplateResponse(
        request,
        "waiting.html",
        {
            "study": state.study.public(),
            "place": {"ahead": place.ahead, "ask_seconds": places.ASK_SECONDS},
            "token": token,
        },
        headers={"Cache-Control": "no-store"},
    )
