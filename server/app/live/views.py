"""The live views of one server: the funnel and the curves, each one ``Broadcast`` for every
dashboard that watches, and one mirror per participant watched (however many watch them); each
read in the live views' own process (``live.reader``) or in the server's."""

from __future__ import annotations

from typing import Any

from server.app.live import curves, funnel, mirror
from server.app.live.broadcast import Broadcast
from server.app.live.reader import UNCHANGED, LiveReader, read_curves, read_funnel, read_mirror
from server.app.state import ServerState
from server.app.storage.models import utcnow


class LiveViews:
    def __init__(self, state: ServerState) -> None:
        self.state = state
        # How often each is computed while watched: BAM_LIVE_FUNNEL_SECONDS and the like.
        self.funnel = Broadcast(self._funnel, state.settings.live_funnel_seconds)
        self.curves = Broadcast(self._curves, state.settings.live_curves_seconds)
        self.mirrors: dict[int, Broadcast] = {}
        url = state.db.engine.url
        in_memory = url.get_backend_name() == "sqlite" and url.database in (None, "", ":memory:")
        self.reader = (
            LiveReader(
                url.render_as_string(hide_password=False),
                state.study,
                state.settings.update_worker_niceness,
            )
            if state.settings.live_reader == "process" and not in_memory
            else None
        )

    async def _funnel(self) -> dict[str, Any]:
        state = self.state
        queue = state.updates.queue() if state.updates is not None else None

        def read() -> dict[str, Any]:
            with state.db.connect() as c:
                return funnel.funnel(c, utcnow())

        if self.reader is not None:
            snapshot = await self.reader.run(read_funnel, utcnow())
        else:
            snapshot = await state.run_db(read)
        snapshot["queue"] = (
            None
            if queue is None
            else {
                "sessions_updating": queue.sessions_updating,
                "sessions_awaited": queue.sessions_awaited,
                "oldest_wait_seconds": round(queue.oldest_wait_seconds, 1),
                "updates_done": queue.completed,
            }
        )
        return snapshot

    async def _curves(self) -> dict[str, Any]:
        if self.reader is not None:
            result: dict[str, Any] = await self.reader.run(read_curves)
            return result

        def read() -> dict[str, Any]:
            with self.state.db.connect() as c:
                return curves.live_curves(c)

        return await self.state.run_db(read)

    def mirror(self, participant_id: int) -> Broadcast:
        """The participant's mirror, shared by everyone who watches them."""
        if participant_id not in self.mirrors:
            if self.reader is not None:
                self.mirrors[participant_id] = self._read_mirror(participant_id, self.reader)
                return self.mirrors[participant_id]
            state = self.state

            async def changed() -> Any:
                def read() -> Any:
                    with state.db.connect() as c:
                        return mirror.fingerprint(c, participant_id)

                return await state.run_db(read)

            async def compute() -> dict[str, Any] | None:
                def read() -> dict[str, Any] | None:
                    with state.db.connect() as c:
                        return mirror.mirror_view(c, state.study, participant_id)

                return await state.run_db(read)

            self.mirrors[participant_id] = Broadcast(
                compute, state.settings.live_mirror_seconds, changed
            )
        return self.mirrors[participant_id]

    def _read_mirror(self, participant_id: int, reader: LiveReader) -> Broadcast:
        """The mirror read in the reader's process: the fingerprint and, when it changed, the
        view, in one round trip (``compute`` returns the view that came with it)."""
        seen: dict[str, Any] = {"fingerprint": None, "view": None}

        async def changed() -> Any:
            fingerprint, view = await reader.run(read_mirror, participant_id, seen["fingerprint"])
            if view != UNCHANGED:
                seen["view"] = view
            seen["fingerprint"] = fingerprint
            return fingerprint

        async def compute() -> dict[str, Any] | None:
            view: dict[str, Any] | None = seen["view"]
            return view

        return Broadcast(compute, self.state.settings.live_mirror_seconds, changed)

    def forget_unwatched(self) -> None:
        for participant_id, broadcast in list(self.mirrors.items()):
            if broadcast.watchers == 0 and not broadcast.running:
                del self.mirrors[participant_id]

    async def stop(self) -> None:
        for broadcast in (self.funnel, self.curves, *self.mirrors.values()):
            await broadcast.stop()
        if self.reader is not None:
            await self.reader.stop()
