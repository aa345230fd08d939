"""The experimenter's sign-in: the admin token, guesses of it limited per client address, and
the dashboard's sessions.

A dashboard session is a random id kept in the database with its expiry (its sha256, so that
reading the table gives no cookie), sent as a cookie signed with a key derived from the admin
token (``id.expiry.signature``). Signing out forgets the id, so a copied cookie stops working;
so does every cookie when the admin token changes. The failed sign-ins are in the database too:
every server of a deployment accepts a cookie any of them gave, and counts an address's
failures on all of them together.
"""

from __future__ import annotations

import hashlib
import hmac
import math
import secrets
import time
from collections.abc import Callable

from fastapi import Request
from sqlalchemy import delete, func, select

from server.app.errors import ApiError
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import DashboardSession, SignInFailure

MIN_ADMIN_TOKEN = 16
SESSION_SECONDS = 12 * 3600
FAILURES_ALLOWED = 10  # failed sign-ins per address in FAILURE_WINDOW seconds, then 429
FAILURE_WINDOW = 60.0


ADMIN_COOKIE = "bam_admin"  # the dashboard session's cookie (see ``AdminSessions``)


def admin_token(settings: Settings) -> str | None:
    token = settings.admin_token
    if token is None or not token.get_secret_value():
        return None
    return token.get_secret_value()


def weak_admin_token(settings: Settings) -> str | None:
    """Why the admin token is not good enough to serve with, or None. Set but empty is refused
    too: it would lock the dashboard as an unset token does, where the experimenter meant to
    open it (an empty variable in a shell or a compose file)."""
    if settings.admin_token is not None and not settings.admin_token.get_secret_value():
        return (
            f"BAM_ADMIN_TOKEN is set but empty: give it a token of {MIN_ADMIN_TOKEN} characters "
            "or more (python3 -c 'import secrets; print(secrets.token_urlsafe())'), or unset it "
            "to serve with the dashboard, the MTurk replica and the admin API locked"
        )
    token = admin_token(settings)
    if token is not None and len(token) < MIN_ADMIN_TOKEN:
        return (
            f"BAM_ADMIN_TOKEN has {len(token)} characters; it needs at least {MIN_ADMIN_TOKEN} "
            "(make one with: python3 -c 'import secrets; print(secrets.token_urlsafe())')"
        )
    return None


def client_address(request: Request) -> str:
    return request.client.host if request.client is not None else "unknown"


class SignInGuard:
    """Failed sign-ins per client address, on every server of the deployment together: past
    ``FAILURES_ALLOWED`` within ``FAILURE_WINDOW`` seconds the address gets 429 (with
    Retry-After) until the oldest failure is that old, whatever it sends, so guessing runs at a
    few tokens a minute. ``clock``: seconds since the epoch (the servers' clocks agree)."""

    def __init__(self, db: Database, clock: Callable[[], float] = time.time) -> None:
        self.db = db
        self.clock = clock

    def check(self, address: str) -> None:
        """429 while ``address`` has used up its failures."""
        now = self.clock()
        with self.db.read() as s:
            count, oldest = s.execute(
                select(func.count(), func.min(SignInFailure.failed_at)).where(
                    SignInFailure.address == address[:64],
                    SignInFailure.failed_at > now - FAILURE_WINDOW,
                )
            ).one()
        if count >= FAILURES_ALLOWED:
            wait = max(1, math.ceil(oldest + FAILURE_WINDOW - now))
            raise ApiError(
                429,
                f"too many failed sign-ins from this address: try again in {wait} s",
                headers={"Retry-After": str(wait)},
            )

    def failed(self, address: str) -> None:
        now = self.clock()
        with self.db.write() as s:
            # Failures past the window count no more: the table keeps only the latest minute.
            s.execute(delete(SignInFailure).where(SignInFailure.failed_at <= now - FAILURE_WINDOW))
            s.add(SignInFailure(address=address[:64], failed_at=now))


class AdminSessions:
    """The dashboard's signed-in sessions (module docstring). ``clock``: seconds since the
    epoch."""

    def __init__(self, db: Database, clock: Callable[[], float] = time.time) -> None:
        self.db = db
        self.clock = clock

    @staticmethod
    def _signature(token: str, payload: str) -> str:
        key = hashlib.sha256(b"bam-study admin session\0" + token.encode()).digest()
        return hmac.new(key, payload.encode(), hashlib.sha256).hexdigest()

    @staticmethod
    def _hash(session_id: str) -> str:
        return hashlib.sha256(session_id.encode()).hexdigest()

    def start(self, token: str) -> str:
        """A new session: the cookie's value."""
        now = self.clock()
        session_id = secrets.token_urlsafe(32)
        expires = int(now) + SESSION_SECONDS
        with self.db.write() as s:
            s.execute(delete(DashboardSession).where(DashboardSession.expires <= now))
            s.add(DashboardSession(id_hash=self._hash(session_id), expires=expires))
        payload = f"{session_id}.{expires}"
        return f"{payload}.{self._signature(token, payload)}"

    def _session_id(self, token: str, cookie: str) -> str | None:
        session_id, _, rest = cookie.partition(".")
        expires, _, signature = rest.partition(".")
        payload = f"{session_id}.{expires}"
        if not secrets.compare_digest(signature.encode(), self._signature(token, payload).encode()):
            return None
        return session_id

    def valid(self, token: str, cookie: str) -> bool:
        session_id = self._session_id(token, cookie)
        if session_id is None:
            return False
        with self.db.read() as s:
            expires = s.scalar(
                select(DashboardSession.expires).where(
                    DashboardSession.id_hash == self._hash(session_id)
                )
            )
        return (
            expires is not None
            and cookie.split(".")[1] == str(expires)
            and (expires > self.clock())
        )

    def end(self, token: str, cookie: str) -> None:
        session_id = self._session_id(token, cookie)
        if session_id is not None:
            with self.db.write() as s:
                s.execute(
                    delete(DashboardSession).where(
                        DashboardSession.id_hash == self._hash(session_id)
                    )
                )


def bearer_is_admin(request: Request, token: str, guard: SignInGuard) -> bool:
    """The request's ``Authorization: Bearer`` is the admin token. A wrong one counts as a
    failed sign-in of its address; an address past its failures gets 429."""
    authorization = request.headers.get("authorization")
    if authorization is None:
        return False
    address = client_address(request)
    guard.check(address)
    scheme, _, given = authorization.partition(" ")
    if scheme.lower() == "bearer" and secrets.compare_digest(given.encode(), token.encode()):
        return True
    guard.failed(address)
    return False


SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})


def own_origin(request: Request) -> str:
    """This server's origin as the browser addressed it (scheme, host and port: behind a
    proxy named in BAM_FORWARDED_ALLOW_IPS, its forwarded scheme); also the replica's
    ``turkSubmitTo``."""
    return f"{request.url.scheme}://{request.url.netloc}"


def request_origin(request: Request) -> str | None:
    """Where the browser says the request comes from: its ``Origin`` (sent by every current
    browser with a POST, PUT, PATCH or DELETE), or where it left that out, its ``Referer``'s
    origin; None from a client that sends neither (a script)."""
    origin = request.headers.get("origin")
    if origin is None:
        referer = request.headers.get("referer")
        if referer is None:
            return None
        scheme, _, rest = referer.partition("://")
        origin = f"{scheme}://{rest.split('/', 1)[0]}"
    return origin.lower()


def from_own_pages(request: Request) -> bool:
    """The request comes from this server's own pages, as the browser says."""
    return request_origin(request) == own_origin(request).lower()


def from_another_site(request: Request) -> bool:
    """The browser says the request comes from another site's page (a script that names no
    origin does not)."""
    origin = request_origin(request)
    return origin is not None and origin != own_origin(request).lower()


def cross_site_refusal() -> ApiError:
    return ApiError(
        403,
        "a signed-in dashboard's changes are accepted only from this server's own pages (the "
        "request's Origin names another site, or none): reload the dashboard, or send the "
        "admin token as a bearer header from a script",
    )


def cookie_is_secure(request: Request, settings: Settings) -> bool:
    """Cookies are sent over HTTPS only where BAM_COOKIE_SECURE says so or the server is
    reached over HTTPS (directly, or behind a named proxy that forwards the scheme)."""
    return settings.cookie_secure or request.url.scheme == "https"
