"""Arrival at the study over the JSON API (the simulated participants, HTTP clients).

The browser arrives through ``GET /study`` (``pages.py``), with the same rules: an MTurk preview
creates nothing; MTurk and Prolific participants are keyed on (worker, assignment) and resumed
when they arrive again, with a new token if their cookie is gone; a worker with another
participation (of any status but returned or declined) is turned away unless the study allows
repeats.
"""

from __future__ import annotations

from fastapi import APIRouter, Request, Response, status

from server.app import flow, places
from server.app.deps import StateDep
from server.app.schemas import ArrivalRequest, ArrivalResponse
from server.app.state import ServerState

router = APIRouter(prefix="/api/arrivals", tags=["participants"])


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


def own_origin(request: Request) -> str:
    """This server's origin as the browser addressed it (the replica's ``turkSubmitTo``)."""
    return f"{request.url.scheme}://{request.url.netloc}"


def arrive(
    state: ServerState, body: ArrivalRequest, request: Request, response: Response
) -> ArrivalResponse:
    """Shared by the API and the page: returns the preview answer or the participant."""
    platform = flow.classify_arrival(body, state.study, state.settings, own_origin(request))
    if platform is None:
        return ArrivalResponse(preview=True)
    cookie = request.cookies.get(state.settings.cookie_name)
    arrival = flow.arrive(state.db, platform, cookie, state.study, places.room_for(state))
    if arrival.token is not None:
        set_participant_cookie(response, state, arrival.token)
    with state.db.connect() as c:
        view = flow.participant_state(c, arrival.participant, state.study)
    return ArrivalResponse(token=arrival.token, resumed=arrival.resumed, participant=view)


@router.post(
    "",
    response_model=ArrivalResponse,
    responses={
        201: {"description": "A new participant."},
    },
)
def create_arrival(
    body: ArrivalRequest, request: Request, response: Response, state: StateDep
) -> ArrivalResponse:
    """Arrive with the platform's parameters (none in a lab). The token is returned once and
    set as a cookie; send it back in the X-Participant-Token header or the cookie."""
    answer = arrive(state, body, request, response)
    if answer.participant is not None and not answer.resumed:
        response.status_code = status.HTTP_201_CREATED
    return answer
