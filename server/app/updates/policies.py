"""The agents' greedy policies, as the update worker stores them, and a cache of the latest one
per learning session so that an agent step needs no learner in the server process."""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Any

import numpy as np
from sqlalchemy import Connection, select
from sqlalchemy.orm import Session

from server.app.storage.models import LearnerUpdate
from server.domains.base import Environment


def encode(policy: np.ndarray) -> bytes:
    """(tasks, states) actions as bytes."""
    return np.ascontiguousarray(policy, dtype=np.int8).tobytes()


def decode(blob: bytes, env: Environment) -> np.ndarray:
    policy = np.frombuffer(blob, dtype=np.int8)
    if policy.size != len(env.tasks) * env.num_states:
        raise ValueError(f"a stored policy has {policy.size} entries, not one per task and state")
    return policy.reshape(len(env.tasks), env.num_states)


class PolicyCache:
    """Latest greedy policy of each session, keyed by the update that produced it."""

    def __init__(self, size: int = 4096) -> None:
        self._size = size
        self._entries: OrderedDict[int, tuple[int, np.ndarray]] = OrderedDict()
        self._lock = threading.Lock()

    def put(self, session_id: int, update_index: int, policy: np.ndarray) -> None:
        with self._lock:
            current = self._entries.get(session_id)
            if current is not None and current[0] > update_index:
                return
            self._entries[session_id] = (update_index, policy)
            self._entries.move_to_end(session_id)
            while len(self._entries) > self._size:
                self._entries.popitem(last=False)

    def get(self, s: Session | Connection, session: Any, env: Environment) -> np.ndarray:
        """The policy of the session's latest done update (read from the database once)."""
        index = session.policy_update
        with self._lock:
            entry = self._entries.get(session.id)
            if entry is not None and entry[0] == index:
                self._entries.move_to_end(session.id)
                return entry[1]
        blob = s.scalar(
            select(LearnerUpdate.greedy_policy).where(
                LearnerUpdate.session_id == session.id, LearnerUpdate.update_index == index
            )
        )
        if blob is None:
            raise LookupError(f"session {session.id} has no stored policy for update {index}")
        policy = decode(blob, env)
        self.put(session.id, int(index or 0), policy)
        return policy
