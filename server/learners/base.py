"""The protocol every learner follows, and the data it learns from.

A learner is taught one environment's tasks. It records what it observes:

- a demonstration step (task, state, action, next state): a teacher action for the task and an
  observed transition;
- an agent step (task, state, action, next state, feedback in {+1, -1, 0}): the agent's own
  action, an observed transition and the teacher's feedback on it (0 = none given);
- an idle move (state, action, next state): the agent was moved without a demonstration (the
  study's idle mode), a transition alone; it tells the learner about the dynamics only.

``update()`` fits the learner to everything recorded so far (warm-started from the previous
update), ``policy(task)`` gives its action probabilities per state and ``greedy_policy(task)``
one action per state. ``state_dict()`` captures the whole learner (data, parameters,
optimiser state, random generator) and ``Learner.from_state_dict(env, state)`` restores it
exactly: the server persists learners between episodes and across restarts.
"""

from __future__ import annotations

import io
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from threadpoolctl import ThreadpoolController

from server.domains.base import Environment
from server.learners.records import (
    AgentStep,
    DemonstrationStep,
    Feedback,
    IdleMove,
    Observation,
)
from server.learners.settings import Settings

_blas: ThreadpoolController | None = None


def one_blas_thread() -> Any:
    """A context in which NumPy's and SciPy's BLAS use one thread. The learners' BLAS calls
    are small (L-BFGS-B's vectors, the pull-back's products): a second OpenBLAS thread never
    has work, but after each call it spins on a core for a while, the core the planner's
    second thread needs (flip, two planner threads: an update took 292 ms, 197 ms with one
    BLAS thread)."""
    global _blas
    if _blas is None:
        _blas = ThreadpoolController()
    return _blas.limit(limits=1, user_api="blas")


# Columns of the recorded-data arrays.
DEMONSTRATION_FIELDS = ("task", "state", "action", "next_state")
AGENT_STEP_FIELDS = ("task", "state", "action", "next_state", "feedback")
IDLE_MOVE_FIELDS = ("state", "action", "next_state")


@dataclass(frozen=True)
class UpdateResult:
    """What one ``update()`` did."""

    seconds: float
    objective: float
    steps: int


class DataLog:
    """Append-only integer tables of demonstrations, agent steps and idle moves."""

    def __init__(self) -> None:
        self._demonstrations: list[tuple[int, ...]] = []
        self._agent_steps: list[tuple[int, ...]] = []
        self._idle_moves: list[tuple[int, ...]] = []

    @staticmethod
    def _table(rows: list[tuple[int, ...]], width: int) -> np.ndarray:
        return np.asarray(rows, dtype=np.int64).reshape(-1, width)

    @property
    def demonstrations(self) -> np.ndarray:
        return self._table(self._demonstrations, len(DEMONSTRATION_FIELDS))

    @property
    def agent_steps(self) -> np.ndarray:
        return self._table(self._agent_steps, len(AGENT_STEP_FIELDS))

    @property
    def idle_moves(self) -> np.ndarray:
        return self._table(self._idle_moves, len(IDLE_MOVE_FIELDS))

    def observed_transitions(self) -> np.ndarray:
        """Every observed (state, action, next_state): D_E of equation (5)."""
        return np.concatenate(
            [
                self.demonstrations[:, 1:4],
                self.agent_steps[:, 1:4],
                self.idle_moves,
            ]
        )

    def state_dict(self) -> dict[str, np.ndarray]:
        return {
            "demonstrations": self.demonstrations,
            "agent_steps": self.agent_steps,
            "idle_moves": self.idle_moves,
        }

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> DataLog:
        log = cls()
        log._demonstrations = [
            tuple(int(v) for v in row) for row in np.asarray(state["demonstrations"]).reshape(-1, 4)
        ]
        log._agent_steps = [
            tuple(int(v) for v in row) for row in np.asarray(state["agent_steps"]).reshape(-1, 5)
        ]
        log._idle_moves = [
            tuple(int(v) for v in row)
            # "transitions_alone": the key of learner states saved before it was "idle_moves".
            for row in np.asarray(
                state["idle_moves"] if "idle_moves" in state else state["transitions_alone"]
            ).reshape(-1, 3)
        ]
        return log


# Settings added after learner states were first saved, each with the value that does what the
# learners did before it existed, so that a state saved without one is restored doing the same:
# an agent in a study that runs across an upgrade keeps its schedule and its arithmetic.
SETTINGS_BEFORE_THEY_EXISTED: dict[str, Any] = {
    # 2026-11-25: the paper authors' choices became the defaults; the ones before them.
    "momentum_clip": "velocity",
    "cost_optimizers": "joint",
    "optimizers": "joint",
    "cost_cells": "every",
    "dynamics_gradient": "exact",
    "variance_floor": 1e-8,
    "q_bound_sds": None,
    "tie_tolerance": 1e-9,
    # 2026-11-27 and 2026-11-28: float64 passes, the whole schedule, NumPy cloning steps.
    "planner_precision": "float64",
    "warm_share": 1.0,
    "compiled_steps": False,
    # 2026-11-29: NumPy steps on the dynamics parameters.
    "compiled_dynamics_steps": False,
}


class _DefaultSettings:
    """A learner class's ``default_settings``: its ``settings_type``'s defaults by name (a new
    dict at each read)."""

    def __get__(self, instance: object, owner: type[Learner]) -> dict[str, Any]:
        return owner.settings_type.defaults()


class Learner(ABC):
    """Base class of every learner (see the module docstring).

    A learner's settings are a frozen dataclass, its ``settings_type``
    (``server.learners.settings``), each field typed and described; ``settings`` holds the
    learner's, read as attributes. ``default_settings`` is the same defaults by name."""

    name: ClassVar[str]
    settings_type: ClassVar[type[Settings]] = Settings
    default_settings = _DefaultSettings()
    settings: Settings
    # Settings that take an update through everything a study's updates do in as few steps as
    # its schedule allows (the same kernels): what ``server.app.updates.warmup`` runs.
    warm_up_settings: ClassVar[dict[str, Any]] = {}

    def __init__(self, env: Environment, seed: int = 0, **settings: Any) -> None:
        names = self.settings_type.names()
        unknown = sorted(set(settings) - set(names))
        if unknown:
            raise ValueError(
                f"unknown setting(s) for learner {self.name!r}: {', '.join(unknown)}; "
                f"valid: {', '.join(sorted(names))}"
            )
        self.env = env
        self.settings = self.settings_type(**settings)
        self.seed = int(seed)
        self.rng = np.random.default_rng(self.seed)
        self.data = DataLog()
        self.updates = 0

    # -- recording ------------------------------------------------------------------------
    def _check_step(self, state: int, action: int, next_state: int) -> tuple[int, int, int]:
        return (
            self.env.check_state(state),
            self.env.check_action(action),
            self.env.check_state(next_state),
        )

    def observe(self, observation: Observation) -> None:
        """Record one observation (``records``): the typed form of the ``record_*`` methods."""
        match observation:
            case DemonstrationStep(task, state, action, next_state):
                self.record_demonstration(task, state, action, next_state)
            case AgentStep(task, state, action, next_state, feedback):
                self.record_agent_step(task, state, action, next_state, feedback)
            case IdleMove(state, action, next_state):
                self.record_idle_move(state, action, next_state)
            case Feedback(feedback):
                self.record_feedback(feedback)
            case _:
                raise TypeError(f"not an observation: {observation!r}")

    def record_demonstration(self, task: int, state: int, action: int, next_state: int) -> None:
        """Record a teacher's action for ``task`` and the transition it made."""
        task = self.env.check_task(task)
        self.data._demonstrations.append((task, *self._check_step(state, action, next_state)))

    def record_agent_step(
        self, task: int, state: int, action: int, next_state: int, feedback: int = 0
    ) -> None:
        """Record the agent's own action for ``task``, the transition it made and the teacher's
        feedback on it (+1, -1, or 0 for none)."""
        task = self.env.check_task(task)
        if feedback not in (-1, 0, 1):
            raise ValueError(f"feedback must be +1, -1 or 0 (none), got {feedback!r}")
        self.data._agent_steps.append(
            (task, *self._check_step(state, action, next_state), int(feedback))
        )

    def record_feedback(self, feedback: int) -> None:
        """Attach feedback to the most recent agent step (the study's +/- keys)."""
        if feedback not in (-1, 1):
            raise ValueError(f"feedback must be +1 or -1, got {feedback!r}")
        if not self.data._agent_steps:
            raise ValueError("there is no agent step to give feedback on")
        *step, _ = self.data._agent_steps[-1]
        self.data._agent_steps[-1] = (*step, int(feedback))

    def record_idle_move(self, state: int, action: int, next_state: int) -> None:
        """Record an idle move (the agent moved without a demonstration): dynamics only."""
        self.data._idle_moves.append(self._check_step(state, action, next_state))

    # -- learning -------------------------------------------------------------------------
    def update(self) -> UpdateResult:
        """Fit to everything recorded so far, warm-started from the previous update."""
        started = time.perf_counter()
        with one_blas_thread():
            objective, steps = self._fit()
        self.updates += 1
        return UpdateResult(time.perf_counter() - started, float(objective), int(steps))

    @abstractmethod
    def _fit(self) -> tuple[float, int]:
        """Fit to all recorded data; return the final objective and the number of steps."""

    @abstractmethod
    def policy(self, task: int) -> np.ndarray:
        """Action probabilities, shape (states, actions)."""

    def greedy_policy(self, task: int) -> np.ndarray:
        """One action per state (ties and states without preference resolved by ``policy``)."""
        probabilities = self.policy(task)
        return np.argmax(probabilities, axis=1).astype(np.int64)

    def act(self, task: int, state: int, rng: np.random.Generator) -> int:
        """The action the agent takes in ``state`` (sampled where the policy is not one-hot)."""
        row = self.policy(task)[self.env.check_state(state)]
        if row.max() >= 1.0:
            return int(np.argmax(row))
        return int(rng.choice(len(row), p=row))

    # -- persistence ----------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """The whole learner (data, parameters, optimiser state, random generator), for
        ``from_state_dict`` or ``dumps``."""
        return {
            "learner": self.name,
            "environment": self.env.name,
            "settings": self.settings.as_dict(),
            "seed": self.seed,
            "updates": self.updates,
            "rng": self.rng.bit_generator.state,
            "data": self.data.state_dict(),
            "parameters": self._parameters_state(),
        }

    @abstractmethod
    def _parameters_state(self) -> dict[str, np.ndarray]:
        """Learned parameters and optimiser state as arrays (copied)."""

    @abstractmethod
    def _load_parameters_state(self, state: dict[str, Any]) -> None:
        """Inverse of ``_parameters_state``."""

    @classmethod
    def from_state_dict(cls, env: Environment, state: dict[str, Any]) -> Learner:
        """The learner ``state_dict`` captured, restored exactly (its data checked again). A
        setting the state lacks, saved before the setting existed, takes the value that does
        what the learner did then (``SETTINGS_BEFORE_THEY_EXISTED``), not today's default."""
        if state.get("learner") != cls.name:
            raise ValueError(f"state is for learner {state.get('learner')!r}, not {cls.name!r}")
        if state.get("environment") != env.name:
            raise ValueError(
                f"state is for environment {state.get('environment')!r}, not {env.name!r}"
            )
        before = {
            key: value
            for key, value in SETTINGS_BEFORE_THEY_EXISTED.items()
            if key in cls.settings_type.names()
        }
        learner = cls(env, seed=state["seed"], **{**before, **state["settings"]})
        learner.updates = int(state["updates"])
        learner.rng.bit_generator.state = state["rng"]
        # Re-record every row through the checks, so corrupt data fails here, clearly.
        stored = DataLog.from_state_dict(state["data"])
        for task, s, a, s2 in stored.demonstrations.tolist():
            learner.record_demonstration(task, s, a, s2)
        for task, s, a, s2, feedback in stored.agent_steps.tolist():
            learner.record_agent_step(task, s, a, s2, feedback)
        for s, a, s2 in stored.idle_moves.tolist():
            learner.record_idle_move(s, a, s2)
        learner._load_parameters_state(
            {key: np.array(value) for key, value in state["parameters"].items()}
        )
        return learner


def dumps(state: dict[str, Any]) -> bytes:
    """Serialise a learner state dict to bytes (compressed NumPy archive plus JSON header)."""
    import json

    arrays: dict[str, np.ndarray] = {}
    for key, value in state["data"].items():
        arrays[f"data/{key}"] = np.asarray(value)
    for key, value in state["parameters"].items():
        arrays[f"parameters/{key}"] = np.asarray(value)
    header = {k: v for k, v in state.items() if k not in ("data", "parameters")}
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)  # type: ignore[arg-type]
    return buffer.getvalue()


def loads(blob: bytes) -> dict[str, Any]:
    """Inverse of ``dumps``."""
    import json

    with np.load(io.BytesIO(blob), allow_pickle=False) as archive:
        header = json.loads(bytes(archive["header"]).decode())
        data = {k.split("/", 1)[1]: archive[k] for k in archive.files if k.startswith("data/")}
        parameters = {
            k.split("/", 1)[1]: archive[k] for k in archive.files if k.startswith("parameters/")
        }
    return {**header, "data": data, "parameters": parameters}
