"""Dependencies shared by the routers, declared once (async: FastAPI would run plain functions
in its thread pool, a thread handoff per dependency and request)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Header, Path, Request

from server.app.admin_auth import (
    ADMIN_COOKIE,
    SAFE_METHODS,
    admin_token,
    bearer_is_admin,
    cross_site_refusal,
    from_own_pages,
)
from server.app.errors import ApiError
from server.app.participants.tokens import TOKEN_HEADER
from server.app.state import ServerState


async def get_state(request: Request) -> ServerState:
    state: ServerState = request.app.state.server
    return state


StateDep = Annotated[ServerState, Depends(get_state)]

# Ids in paths: a row id of the database (PostgreSQL's integer is 32-bit), so that a larger
# number is refused here and never reaches the database driver.
MAX_ROW_ID = 2**31 - 1
RowId = Annotated[int, Path(ge=1, le=MAX_ROW_ID, description="A row id.")]


async def participant_token(
    request: Request,
    state: StateDep,
    token: Annotated[str | None, Header(alias=TOKEN_HEADER)] = None,
) -> str | None:
    """The participant's token: the header (HTTP clients) or the cookie (the browser)."""
    return token or request.cookies.get(state.settings.cookie_name)


TokenDep = Annotated[str | None, Depends(participant_token)]


def is_admin(request: Request, state: ServerState) -> bool:
    """The request carries the admin token (bearer header) or a dashboard session's cookie
    (SameSite=Strict, so another site's page cannot send it). A change made with the cookie
    must also come from this server's own pages (its Origin): a 403 otherwise, whatever a
    browser's SameSite rules or a proxy's headers let through."""
    expected = admin_token(state.settings)
    if expected is None:
        return False
    if bearer_is_admin(request, expected, state.sign_ins):
        return True
    cookie = request.cookies.get(ADMIN_COOKIE)
    if cookie is None or not state.admin_sessions.valid(expected, cookie):
        return False
    if request.method not in SAFE_METHODS and not from_own_pages(request):
        raise cross_site_refusal()
    return True


async def require_admin(request: Request, state: StateDep) -> None:
    """The admin API, for a script with the token and for the dashboard signed in."""
    if admin_token(state.settings) is None:
        raise ApiError(503, "the admin API is disabled: set BAM_ADMIN_TOKEN")
    if not is_admin(request, state):
        raise ApiError(
            401,
            "admin token missing or wrong, or the dashboard is not signed in",
            headers={"WWW-Authenticate": "Bearer"},
        )


AdminDep = Depends(require_admin)
