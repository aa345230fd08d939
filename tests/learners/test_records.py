"""The typed observations a learner is handed: checked once where made, and observed exactly as
the ``record_*`` calls they stand for."""

from __future__ import annotations

import numpy as np
import pytest

from server import domains, learners
from server.learners.records import AgentStep, DemonstrationStep, Feedback, IdleMove


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: DemonstrationStep(0, -1, 2, 3), "state must not be negative"),
        (lambda: DemonstrationStep(0, 1, True, 3), "action must be an integer"),
        (lambda: IdleMove(1.0, 2, 3), "state must be an integer"),  # type: ignore[arg-type]
        (lambda: AgentStep(0, 1, 2, 3, feedback=2), "feedback must be"),
        (lambda: AgentStep(0, 1, 2, 3, feedback=True), "feedback must be an integer"),
        (lambda: Feedback(0), "feedback must be \\+1 or -1"),
    ],
)
def test_a_malformed_observation_is_refused_where_it_is_made(make, message) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ValueError, match=message):
        make()


def test_numpy_integers_are_stored_as_python_integers() -> None:
    step = DemonstrationStep(np.int64(1), np.int32(2), np.int64(3), np.int16(4))
    assert step == DemonstrationStep(1, 2, 3, 4)
    assert all(type(value) is int for value in (step.task, step.state, step.action))


def test_observe_records_what_the_record_calls_record() -> None:
    env = domains.make("doorway")
    rng = np.random.default_rng(0)
    observations = []
    for task in range(len(env.tasks)):
        state = env.sample_start(task, rng)
        for action in (1, 2, 3):
            next_state = env.step(state, action, rng)
            observations.append(DemonstrationStep(task, state, action, next_state))
            observations.append(AgentStep(task, next_state, action, state))
            observations.append(Feedback(-1 if action == 2 else 1))
            observations.append(IdleMove(state, action, next_state))
            state = next_state
    typed = learners.make("bam", env, seed=0)
    for observation in observations:
        typed.observe(observation)
    called = learners.make("bam", env, seed=0)
    for o in observations:
        if isinstance(o, DemonstrationStep):
            called.record_demonstration(o.task, o.state, o.action, o.next_state)
        elif isinstance(o, AgentStep):
            called.record_agent_step(o.task, o.state, o.action, o.next_state, o.feedback)
        elif isinstance(o, Feedback):
            called.record_feedback(o.feedback)
        else:
            called.record_idle_move(o.state, o.action, o.next_state)
    for name, table in typed.data.state_dict().items():
        assert np.array_equal(table, called.data.state_dict()[name]), name
    assert set(typed.data.agent_steps[:, 4].tolist()) == {-1, 1}
    with pytest.raises(TypeError, match="not an observation"):
        typed.observe(("demonstration", 0, 1, 2, 3))  # type: ignore[arg-type]


def test_a_state_saved_with_the_old_name_of_idle_moves_still_loads() -> None:
    env = domains.make("doorway")
    learner = learners.make("model-based", env, seed=0)
    learner.observe(IdleMove(5, 2, 14))
    learner.observe(DemonstrationStep(0, 5, 2, 14))
    state = learner.state_dict()
    state["data"]["transitions_alone"] = state["data"].pop("idle_moves")
    restored = learners.restore(env, state)
    np.testing.assert_array_equal(restored.data.idle_moves, [[5, 2, 14]])
