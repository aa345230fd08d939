"""One snapshot per interval for every watcher: a ``Broadcast`` computes its snapshot once per
``interval`` while someone watches (none: it stops), and each watcher gets the latest as soon
as it changes. A thousand dashboards cost the server what one does."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any

log = logging.getLogger("bam_study")

# A comment line sent when nothing changed for this long, so that proxies keep the stream open.
KEEPALIVE_SECONDS = 15.0


class Broadcast:
    """``compute()`` (a coroutine: a JSON-ready snapshot, or None when there is nothing to
    show) run every ``interval`` seconds while anyone watches; ``changed`` (optional, cheaper)
    says whether it is worth computing again."""

    def __init__(
        self,
        compute: Callable[[], Awaitable[dict[str, Any] | None]],
        interval: float,
        changed: Callable[[], Awaitable[Any]] | None = None,
    ) -> None:
        self.compute = compute
        self.changed = changed
        self.interval = interval
        self.version = 0
        self.latest: str | None = None  # the latest snapshot as JSON
        self.computed = 0  # how many snapshots were computed (for the tests and benchmarks)
        self.watchers = 0
        self._fingerprint: Any = object()
        self._news = asyncio.Event()
        self._task: asyncio.Task[None] | None = None

    @property
    def running(self) -> bool:
        return self._task is not None

    async def _run(self) -> None:
        while self.watchers > 0:
            try:
                await self._tick()
            except Exception:
                log.exception("could not compute a live view")
            await asyncio.sleep(self.interval)
        self._task = None

    async def _tick(self) -> None:
        if self.changed is not None:
            fingerprint = await self.changed()
            if fingerprint == self._fingerprint and self.latest is not None:
                return
            self._fingerprint = fingerprint
        snapshot = await self.compute()
        self.computed += 1
        text = json.dumps(snapshot, separators=(",", ":"))
        if text != self.latest:
            self.latest = text
            self.version += 1
            news, self._news = self._news, asyncio.Event()
            news.set()

    async def watch(self, event: str) -> AsyncIterator[str]:
        """The stream of server-sent events: the latest snapshot at once, then each new one."""
        self.watchers += 1
        if self._task is None:
            self._task = asyncio.ensure_future(self._run())
        try:
            seen = 0
            while True:
                if self.version != seen and self.latest is not None:
                    seen = self.version
                    yield f"event: {event}\nid: {seen}\ndata: {self.latest}\n\n"
                    continue
                news = self._news
                try:
                    await asyncio.wait_for(news.wait(), KEEPALIVE_SECONDS)
                except TimeoutError:
                    yield ": still here\n\n"
        finally:
            self.watchers -= 1

    async def stop(self) -> None:
        self.watchers = 0
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
