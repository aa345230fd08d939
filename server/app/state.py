"""What every request of one running server shares: the database, the study, the settings,
the cache of agents' policies and the learner-update manager."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, TypeVar

from starlette.concurrency import run_in_threadpool

from server.app.admin_auth import AdminSessions, SignInGuard
from server.app.platforms.backends import make_backend
from server.app.platforms.review import ReviewBackend
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.study_file import StudyConfig
from server.app.updates.policies import PolicyCache

if TYPE_CHECKING:
    from server.app.updates.manager import UpdateManager

T = TypeVar("T")


@dataclass
class ServerState:
    db: Database
    study: StudyConfig
    settings: Settings
    policies: PolicyCache = field(default_factory=PolicyCache)
    updates: UpdateManager | None = None
    # In the database: every server of a deployment shares them (``admin_auth``).
    sign_ins: SignInGuard = field(init=False)
    admin_sessions: AdminSessions = field(init=False)
    # By the participants' platform (mturk, prolific), each made on first use.
    reviews: dict[str, ReviewBackend] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.sign_ins = SignInGuard(self.db)
        self.admin_sessions = AdminSessions(self.db)

    def review_backend(self, platform: str) -> ReviewBackend:
        """Where the reviews and bonuses of the platform's participants go
        (``BAM_REVIEW_BACKEND``)."""
        if platform not in self.reviews:
            self.reviews[platform] = make_backend(self.settings, self.db, platform)
        return self.reviews[platform]

    async def run_db(self, work: Callable[[], T]) -> T:
        """Run a short database transaction for a request. On SQLite, in the event loop itself:
        its writes are serialised anyway, and a thread handoff per request costs more (GIL
        handoffs) than the transaction; on PostgreSQL, in the thread pool, so that the
        transactions of different participants run in parallel."""
        if self.db.is_sqlite:
            return work()
        return await run_in_threadpool(work)
