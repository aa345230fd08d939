"""The protocol every learner follows (``server.learners.make``): recording and validating
data, valid policies, exact save/restore, bounded state size, and learning from simulated
demonstrations."""

from __future__ import annotations

import copy
from typing import Any

import numpy as np
import pytest

from server import domains, learners
from server.learners import dumps, loads
from server.learners.base import Learner
from server.learners.evaluation import normalized_return
from server.teacher import Teacher
from tests.learners._support import agent_episode, demonstrate_round, idle_transitions


def teach_round(learner: Learner, teacher: Teacher, rng: np.random.Generator) -> None:
    """A round of the demonstrations-and-feedback experiment, shortened: a demonstration per
    task, a few agent steps with feedback on each task, and some idle moves."""
    env = learner.env
    demonstrate_round(learner, env, teacher, rng)
    for task in range(len(env.tasks)):
        agent_episode(learner, env, teacher, rng, task, steps=6)
    idle_transitions(learner, env, rng, count=5)


def assert_same_state(first: Any, second: Any, path: str = "state") -> None:
    """Exact equality of two (nested) learner states."""
    if isinstance(first, dict):
        assert isinstance(second, dict) and set(first) == set(second), path
        for key in first:
            assert_same_state(first[key], second[key], f"{path}/{key}")
    elif isinstance(first, np.ndarray | list | tuple) and not isinstance(first, str):
        a, b = np.asarray(first), np.asarray(second)
        assert a.shape == b.shape, path
        assert np.array_equal(a, b), path
    else:
        assert first == second, path


# -- the registry (its order and entries: test_registry.py) ---------------------------------------


def test_registry_names() -> None:
    env = domains.make("wall")
    for name in learners.NAMES:
        learner = learners.make(name, env)
        assert learner.name == name and learner.env is env


def test_unknown_learner_name_lists_the_valid_ones() -> None:
    with pytest.raises(ValueError, match="unknown learner") as error:
        learners.make("bma", domains.make("wall"))
    for name in learners.NAMES:
        assert name in str(error.value)


@pytest.mark.parametrize("name", learners.NAMES)
def test_settings_default_to_the_reference_and_can_be_overridden(name: str) -> None:
    env = domains.make("wall")
    learner = learners.make(name, env)
    reference = {"beta": 1.0, "epsilon": 0.05, "alpha": 1.0, "mu_plus": 0.1, "mu_minus": 0.1}
    for key, value in reference.items():
        assert getattr(learner.settings, key) == value, key
    assert learner.settings.normalized_actions is True
    overridden = learners.make(name, env, beta=2.0, epsilon=0.1)
    assert overridden.settings.beta == 2.0 and overridden.settings.epsilon == 0.1
    with pytest.raises(ValueError, match="unknown setting"):
        learners.make(name, env, betta=2.0)


def test_reference_optimisation_settings() -> None:
    env = domains.make("wall")
    planner = learners.make("bam", env)
    assert planner.settings.cost_prior_sd == 1.0 and planner.settings.cost_bound == 3.0
    assert (planner.settings.alternations, planner.settings.cost_steps) == (10, 20)
    assert planner.settings.dynamics_steps == 20
    assert np.all(planner.theta == -3.0)  # navigation cells presumed free
    model_based = learners.make("model-based", env)
    assert (model_based.settings.dynamics_steps, model_based.settings.cost_steps) == (
        200,
        200,
    )
    # Warm updates run part of the schedule (docs/defaults.md, "Shorter warm updates");
    # the global-cost learner, not run through its experiment so, the whole of it.
    assert planner.settings.warm_share == 0.7 and model_based.settings.warm_share == 0.5
    assert learners.make("global-cost", env).settings.warm_share == 1.0


# -- policies --------------------------------------------------------------------------------------


def assert_valid_policies(learner: Learner) -> None:
    env = learner.env
    for task in range(len(env.tasks)):
        policy = learner.policy(task)
        assert policy.shape == (env.num_states, env.num_actions)
        assert np.all(policy >= 0.0)
        np.testing.assert_allclose(policy.sum(axis=1), 1.0, rtol=0, atol=1e-12)
        greedy = learner.greedy_policy(task)
        assert greedy.shape == (env.num_states,)
        assert np.all((greedy >= 0) & (greedy < env.num_actions))


@pytest.mark.parametrize("name", learners.NAMES)
def test_policies_are_valid_before_and_after_updates(name: str) -> None:
    env = domains.make("wall")
    learner = learners.make(name, env, seed=0)
    assert_valid_policies(learner)
    learner.update()  # no data at all
    assert_valid_policies(learner)
    teach_round(learner, Teacher(env, seed=1), np.random.default_rng(1))
    result = learner.update()
    assert np.isfinite(result.objective) and result.steps > 0 and result.seconds >= 0.0
    assert learner.updates == 2
    assert_valid_policies(learner)


def test_cloning_acts_at_random_where_it_has_no_data() -> None:
    env = domains.make("wall")
    learner = learners.make("cloning", env, seed=0)
    rng = np.random.default_rng(2)
    rows = demonstrate_round(learner, env, Teacher(env, seed=2), rng)
    learner.update()
    for task in range(len(env.tasks)):
        seen = {state for t, state, _, _ in rows if t == task}
        policy = learner.policy(task)
        for state in range(env.num_states):
            if state in seen:
                assert policy[state].max() == 1.0
            else:
                np.testing.assert_allclose(policy[state], 1.0 / env.num_actions)
        # It follows the demonstrated actions where it has them.
        for t, state, action, _ in rows:
            if t == task:
                assert policy[state, action] == 1.0


def test_cloning_splits_evenly_between_actions_tied_for_best() -> None:
    """A state whose only data is "-" on one action leaves the other four exactly tied: the
    agent must try them, not take the first (STAY) for ever."""
    env = domains.make("wall")
    up, left = 1, 3
    state, other = 30, 31
    learner = learners.make("cloning", env, seed=0)
    learner.record_agent_step(0, state, up, env.step(state, up, np.random.default_rng(0)), -1)
    learner.record_agent_step(0, other, left, env.step(other, left, np.random.default_rng(0)), 1)
    learner.update()
    policy = learner.policy(0)
    expected = np.full(env.num_actions, 0.25)
    expected[up] = 0.0
    np.testing.assert_allclose(policy[state], expected)
    assert policy[other, left] == 1.0
    chosen = {int(learner.greedy_policy(0)[state]) for _ in range(60)}
    assert chosen == set(range(env.num_actions)) - {up}
    assert {int(learner.greedy_policy(0)[other]) for _ in range(10)} == {left}


# -- recording and bad input ----------------------------------------------------------------------


@pytest.mark.parametrize("name", learners.NAMES)
def test_recorded_data_is_kept(name: str) -> None:
    env = domains.make("wall")
    learner = learners.make(name, env)
    learner.record_demonstration(1, 10, 4, 11)
    learner.record_agent_step(0, 11, 3, 10, feedback=1)
    learner.record_agent_step(0, 10, 1, 1)
    learner.record_feedback(-1)
    learner.record_idle_move(np.int64(5), np.int64(2), np.int64(14))
    np.testing.assert_array_equal(learner.data.demonstrations, [[1, 10, 4, 11]])
    np.testing.assert_array_equal(learner.data.agent_steps, [[0, 11, 3, 10, 1], [0, 10, 1, 1, -1]])
    np.testing.assert_array_equal(learner.data.idle_moves, [[5, 2, 14]])


BAD_STEPS = [
    # (task, state, action, next_state, what the message names)
    (2, 10, 4, 11, "task"),
    (-1, 10, 4, 11, "task"),
    (0.0, 10, 4, 11, "task"),
    (0, 81, 4, 11, "state"),
    (0, -1, 4, 11, "state"),
    (0, 1.5, 4, 11, "state"),
    (0, "10", 4, 11, "state"),
    (0, None, 4, 11, "state"),
    (0, 10, 5, 11, "action"),
    (0, 10, -1, 11, "action"),
    (0, 10, 4.0, 11, "action"),
    (0, 10, 4, 81, "state"),
    (0, 10, 4, 2.5, "state"),
]


@pytest.mark.parametrize("name", learners.NAMES)
@pytest.mark.parametrize(("task", "state", "action", "next_state", "match"), BAD_STEPS)
def test_bad_records_are_rejected_and_not_kept(
    name: str, task: Any, state: Any, action: Any, next_state: Any, match: str
) -> None:
    learner = learners.make(name, domains.make("wall"))
    with pytest.raises(ValueError, match=match):
        learner.record_demonstration(task, state, action, next_state)
    with pytest.raises(ValueError, match=match):
        learner.record_agent_step(task, state, action, next_state, 1)
    if match != "task":
        with pytest.raises(ValueError, match=match):
            learner.record_idle_move(state, action, next_state)
    assert len(learner.data.demonstrations) == 0
    assert len(learner.data.agent_steps) == 0
    assert len(learner.data.idle_moves) == 0


@pytest.mark.parametrize("name", learners.NAMES)
def test_bad_feedback_is_rejected(name: str) -> None:
    learner = learners.make(name, domains.make("wall"))
    with pytest.raises(ValueError, match="no agent step"):
        learner.record_feedback(1)
    for feedback in (2, -2, 0.5):
        with pytest.raises(ValueError, match="feedback"):
            learner.record_agent_step(0, 10, 4, 11, feedback)
    learner.record_agent_step(0, 10, 4, 11)
    for feedback in (0, 2, -3, 0.5):
        with pytest.raises(ValueError, match="feedback"):
            learner.record_feedback(feedback)
    np.testing.assert_array_equal(learner.data.agent_steps, [[0, 10, 4, 11, 0]])


# -- save and restore --------------------------------------------------------------------------


@pytest.mark.parametrize("name", learners.NAMES)
def test_save_and_restore_round_trips_exactly(name: str) -> None:
    env = domains.make("wall")
    original = learners.make(name, env, seed=3, beta=1.5)
    teach_round(original, Teacher(env, seed=3), np.random.default_rng(3))
    original.update()
    state = original.state_dict()
    snapshot = copy.deepcopy(state)
    blob = dumps(state)
    assert isinstance(blob, bytes)
    restored = [learners.restore(env, state), learners.restore(env, loads(blob))]
    for learner in restored:
        assert type(learner) is type(original)
        assert learner.settings == original.settings and learner.updates == original.updates
        assert_same_state(learner.state_dict(), state)
    copies = [original, *restored]
    for task in range(len(env.tasks)):
        policies = [learner.policy(task) for learner in copies]
        greedy = [learner.greedy_policy(task) for learner in copies]
        for policy, actions in zip(policies[1:], greedy[1:], strict=True):
            np.testing.assert_array_equal(policy, policies[0])
            np.testing.assert_array_equal(actions, greedy[0])
    # The same new data and one more update leave all three in the same state.
    for learner in copies:
        teach_round(learner, Teacher(env, seed=4), np.random.default_rng(4))
        learner.update()
    final = original.state_dict()
    assert final["data"]["demonstrations"].shape[0] > state["data"]["demonstrations"].shape[0]
    for learner in restored:
        assert_same_state(learner.state_dict(), final)
        for task in range(len(env.tasks)):
            np.testing.assert_array_equal(learner.policy(task), original.policy(task))
    # A state dict is a snapshot: learning afterwards does not change it.
    assert_same_state(state, snapshot)
    with pytest.raises(AssertionError):
        assert_same_state(final["parameters"], state["parameters"])


def with_nan(state: dict[str, Any], key: str) -> dict[str, Any]:
    broken = copy.deepcopy(state)
    array = np.array(broken["parameters"][key], dtype=np.float64)
    array.flat[0] = np.nan
    broken["parameters"][key] = array
    return broken


@pytest.mark.parametrize("name", learners.NAMES)
def test_restoring_bad_states_is_rejected(name: str) -> None:
    env = domains.make("wall")
    learner = learners.make(name, env, seed=0)
    teach_round(learner, Teacher(env, seed=5), np.random.default_rng(5))
    learner.update()
    state = learner.state_dict()
    float_arrays = [
        key
        for key, value in state["parameters"].items()
        if np.asarray(value).dtype.kind == "f" and np.asarray(value).size
    ]
    assert float_arrays
    for key in float_arrays:
        with pytest.raises(ValueError, match="NaN or infinite"):
            learners.restore(env, with_nan(state, key))
        with pytest.raises(ValueError):
            learners.restore(env, loads(dumps(with_nan(state, key))))
    with pytest.raises(ValueError, match="environment"):
        learners.restore(domains.make("doorway"), state)
    with pytest.raises(ValueError, match="unknown learner"):
        learners.restore(env, {**state, "learner": "nonsense"})
    other = next(n for n in learners.NAMES if n != name)
    with pytest.raises(ValueError, match="learner"):
        learners.learner_class(other).from_state_dict(env, state)
    first = next(iter(state["parameters"]))
    wrong_shape = copy.deepcopy(state)
    wrong_shape["parameters"][first] = np.zeros(3)
    with pytest.raises(ValueError, match="shape"):
        learners.restore(env, wrong_shape)


@pytest.mark.parametrize("name", learners.NAMES)
def test_restoring_out_of_range_data_is_rejected(name: str) -> None:
    env = domains.make("wall")
    learner = learners.make(name, env, seed=0)
    teach_round(learner, Teacher(env, seed=6), np.random.default_rng(6))
    state = learner.state_dict()
    for table, column, bad in (
        ("demonstrations", 1, env.num_states),
        ("demonstrations", 2, env.num_actions),
        ("demonstrations", 0, len(env.tasks)),
        ("agent_steps", 4, 2),
        ("idle_moves", 2, -1),
    ):
        broken = copy.deepcopy(state)
        rows = np.array(broken["data"][table])
        rows[0, column] = bad
        broken["data"][table] = rows
        with pytest.raises(ValueError):
            learners.restore(env, broken)


@pytest.mark.slow
@pytest.mark.parametrize("environment", ["flip", "two-fields"])
@pytest.mark.parametrize("name", learners.NAMES)
def test_state_after_ten_rounds_is_under_five_megabytes(name: str, environment: str) -> None:
    env = domains.make(environment)
    learner = learners.make(name, env, seed=0)
    teacher = Teacher(env, seed=0)
    rng = np.random.default_rng(0)
    for _ in range(10):
        teach_round(learner, teacher, rng)
        learner.update()
    size = len(dumps(learner.state_dict()))
    assert size < 5 * 1024 * 1024
    assert learners.restore(env, loads(dumps(learner.state_dict()))).updates == 10


# -- learning ------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("environment", ["doorway", "two-fields"])
@pytest.mark.parametrize("name", learners.NAMES)
def test_three_rounds_of_demonstrations_improve_the_return(name: str, environment: str) -> None:
    env = domains.make(environment)
    learner = learners.make(name, env, seed=0)
    before = normalized_return(env, learner)
    teacher = Teacher(env, seed=0)
    rng = np.random.default_rng(0)
    for _ in range(3):
        demonstrate_round(learner, env, teacher, rng)
        learner.update()
    after = normalized_return(env, learner)
    assert 0.0 <= before <= 1.0 and after <= 1.0 + 1e-9
    assert after > before + 0.1, (before, after)


@pytest.mark.parametrize("name", learners.NAMES)
def test_an_update_runs_with_one_blas_thread_and_restores_the_count(
    name: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An update's BLAS calls run on one thread (an idle OpenBLAS thread spins on the core
    the planner's second thread needs) and the process's BLAS thread counts are as before
    afterwards."""
    from threadpoolctl import threadpool_info

    def blas_threads() -> list[int]:
        return [pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"]

    before = blas_threads()
    assert before, "NumPy and SciPy load a BLAS"
    learner = learners.make(name, domains.make("wall"))
    seen: list[list[int]] = []
    fit = learner._fit
    monkeypatch.setattr(learner, "_fit", lambda: (seen.append(blas_threads()), fit())[1])
    learner.update()
    assert seen == [[1] * len(before)]
    assert blas_threads() == before
