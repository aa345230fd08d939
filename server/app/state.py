"""What every request of one running server shares: the database, the study, the settings,
the cache of agents' policies and the learner-update manager."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, TypeVar

from starlette.concurrency import run_in_threadpool

from server.app.admin_auth import AdminSessions, SignInGuard
from server.app.config import StudyConfig
from server.app.platforms.review import ReviewBackend, make_backend
from server.app.settings import Settings
from server.app.storage.db import Database
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
    sign_ins: SignInGuard = field(default_factory=SignInGuard)
    admin_sessions: AdminSessions = field(default_factory=AdminSessions)
    review: ReviewBackend | None = None  # made on first use (BAM_REVIEW_BACKEND)

    def review_backend(self) -> ReviewBackend:
        """The platform the experimenter's reviews and bonuses go to."""
        if self.review is None:
            self.review = make_backend(self.settings, self.db)
        return self.review

    async def run_db(self, work: Callable[[], T]) -> T:
        """Run a short database transaction for a request. On SQLite, in the event loop itself:
        its writes are serialised anyway, and a thread handoff per request costs more (GIL
        handoffs) than the transaction; on PostgreSQL, in the thread pool, so that the
        transactions of different participants run in parallel."""
        if self.db.is_sqlite:
            return work()
        return await run_in_threadpool(work)
