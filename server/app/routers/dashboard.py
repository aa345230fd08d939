"""The experimenter's dashboard: an HTML page behind the admin token.

Signing in with ``BAM_ADMIN_TOKEN`` starts a dashboard session (``admin_auth``): an HttpOnly,
SameSite=Strict cookie with a random id, its expiry and a signature, which signing out revokes.
The dashboard's page calls the admin API (``/api/admin``), which accepts that cookie as well as
``Authorization: Bearer``. Failed sign-ins are limited per address.
"""

from __future__ import annotations

import secrets
from typing import Annotated

from fastapi import APIRouter, Form, Query, Request, Response
from fastapi.responses import HTMLResponse, RedirectResponse

from server.app.admin_auth import (
    ADMIN_COOKIE,
    SESSION_SECONDS,
    admin_token,
    client_address,
    cookie_is_secure,
    cross_site_refusal,
    from_another_site,
)
from server.app.deps import StateDep, is_admin
from server.app.errors import ApiError
from server.app.routers.common import login_redirect, templates
from server.app.state import ServerState


def safe_next(target: str | None) -> str:
    """Only paths on this server (no scheme, no host) are followed after signing in."""
    if target and target.startswith("/") and not target.startswith("//") and "\\" not in target:
        return target
    return "/dashboard"


def login_page(
    request: Request,
    state: ServerState,
    next_path: str,
    error: str | None,
    status_code: int = 401,
    headers: dict[str, str] | None = None,
) -> Response:
    disabled = admin_token(state.settings) is None
    return templates.TemplateResponse(
        request,
        "dashboard_login.html",
        {"next": safe_next(next_path), "error": error, "disabled": disabled},
        status_code=status_code if error else (503 if disabled else 200),
        headers={"Cache-Control": "no-store", **(headers or {})},
    )


pages = APIRouter(tags=["dashboard"], include_in_schema=False)


@pages.get("/dashboard", response_class=HTMLResponse)
def dashboard_page(request: Request, state: StateDep) -> Response:
    if not is_admin(request, state):
        return login_redirect("/dashboard")
    return templates.TemplateResponse(
        request,
        "dashboard.html",
        {"study": state.study.public()},
        headers={"Cache-Control": "no-store"},
    )


@pages.get("/dashboard/login", response_class=HTMLResponse)
def dashboard_login_form(
    request: Request, state: StateDep, next: Annotated[str, Query()] = "/dashboard"
) -> Response:
    if is_admin(request, state):
        return RedirectResponse(safe_next(next), status_code=303)
    return login_page(request, state, next, None)


@pages.post("/dashboard/login", response_class=HTMLResponse)
def dashboard_login(
    request: Request,
    state: StateDep,
    token: Annotated[str, Form(max_length=512)],
    next: Annotated[str, Form(max_length=512)] = "/dashboard",
) -> Response:
    expected = admin_token(state.settings)
    if expected is None:
        return login_page(request, state, next, None)
    if from_another_site(request):  # another site signing the browser in to a session
        raise cross_site_refusal()
    address = client_address(request)
    try:
        state.sign_ins.check(address)
    except ApiError as refused:
        return login_page(request, state, next, refused.message, 429, refused.headers)
    if not secrets.compare_digest(token.strip().encode(), expected.encode()):
        state.sign_ins.failed(address)
        return login_page(request, state, next, "That is not the admin token.")
    response = RedirectResponse(safe_next(next), status_code=303)
    response.set_cookie(
        ADMIN_COOKIE,
        state.admin_sessions.start(expected),
        max_age=SESSION_SECONDS,
        httponly=True,
        samesite="strict",
        secure=cookie_is_secure(request, state.settings),
    )
    return response


@pages.post("/dashboard/logout")
def dashboard_logout(request: Request, state: StateDep) -> Response:
    """Sign out: the session is revoked (a copy of its cookie stops working too)."""
    expected = admin_token(state.settings)
    cookie = request.cookies.get(ADMIN_COOKIE)
    if expected is not None and cookie is not None:
        state.admin_sessions.end(expected, cookie)
    response = RedirectResponse("/dashboard/login", status_code=303)
    response.delete_cookie(ADMIN_COOKIE)
    return response
