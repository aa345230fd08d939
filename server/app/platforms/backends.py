"""The review backend for a platform's participants, as ``BAM_REVIEW_BACKEND`` chooses:
``replica`` (the local replica of the participants' platform) or a platform's name (that
platform's own API: Mechanical Turk through boto3, Prolific's API); each platform makes its own
(``Platform.review_backend``)."""

from __future__ import annotations

from server.app.errors import ApiError
from server.app.platform_registry import platform
from server.app.platforms.review import ReviewBackend
from server.app.settings import Settings
from server.app.storage.db import Database


def make_backend(settings: Settings, db: Database, name: str) -> ReviewBackend:
    chosen = settings.review_backend
    if chosen in ("replica", name):
        backend = platform(name).review_backend(settings, db, replica=chosen == "replica")
        if backend is not None:
            return backend
    raise ApiError(
        409,
        f"the review backend is {chosen} (BAM_REVIEW_BACKEND), which does not review "
        f"participants who came from {name}",
    )
