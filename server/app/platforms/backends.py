"""The review backend for a platform's participants, as ``BAM_REVIEW_BACKEND`` chooses:
``replica`` (the local replica of the participants' platform), ``mturk`` (Mechanical Turk
through boto3) or ``prolific`` (Prolific's API)."""

from __future__ import annotations

from server.app.errors import ApiError
from server.app.platforms.mturk import MTurkClientBackend, MTurkReplicaBackend, mturk_client
from server.app.platforms.prolific import ProlificBackend, ProlificClient
from server.app.platforms.prolific_replica import ReplicaTransport
from server.app.platforms.review import ReviewBackend
from server.app.settings import Settings
from server.app.storage.db import Database


def make_backend(settings: Settings, db: Database, platform: str) -> ReviewBackend:
    chosen = settings.review_backend
    if chosen == "replica":
        if platform == "mturk":
            return MTurkReplicaBackend(db)
        if platform == "prolific":
            # Prolific's client, answered by the replica inside the server.
            token = settings.admin_token.get_secret_value() if settings.admin_token else ""
            client = ProlificClient(
                "http://replica/prolific/api/v1", token, transport=ReplicaTransport(db, token)
            )
            return ProlificBackend(client, settings.prolific_currency, name="prolific-replica")
    elif chosen == platform == "mturk":
        return MTurkClientBackend(mturk_client(settings))
    elif chosen == platform == "prolific":
        if settings.prolific_token is None:
            raise ApiError(503, "BAM_REVIEW_BACKEND=prolific needs BAM_PROLIFIC_TOKEN")
        client = ProlificClient(
            settings.prolific_api_url, settings.prolific_token.get_secret_value()
        )
        return ProlificBackend(client, settings.prolific_currency)
    raise ApiError(
        409,
        f"the review backend is {chosen} (BAM_REVIEW_BACKEND), which does not review "
        f"participants who came from {platform}",
    )
