"""The learners' compiled kernels loaded before anyone waits on them.

numba compiles the planner's and the likelihoods' kernels on their first call and keeps them in
its on-disk cache: a process loads them on its first update (about 0.3 s), and on a machine
whose cache is missing or was made for another CPU (a new container, a new checkout) compiles
them (about a minute of a core; docs/benchmarks.md has the figure). A study server's update
processes run ``warm_up`` when they start, so that neither lands on a participant's first
update; processes that start together compile different kernels side by side
(``compiling``)."""

from __future__ import annotations

import time

import numpy as np

from server import domains, learners
from server.domains.base import STAY, Environment
from server.learners import make, restore
from server.learners.evaluation import normalized_return
from server.learners.planner_learner import PlannerLearner
from server.learners.planning import using_planner_threads
from server.teacher import Teacher

# One environment of each domain (navigation, farming, gravity), each with several tasks so
# that a pass can split over threads.
ENVIRONMENTS = ("navigation-tutorial", "farming-tutorial", "gravity-tutorial")


def warm_up_plan(
    order: int = 0, thread_counts: tuple[int, ...] = (1, 2)
) -> list[tuple[int, str, str]]:
    """What ``warm_up`` goes through, as (planner threads, environment, learner): every
    combination, in one of two orders. Order 0 goes from one thread, the first environment and
    the first learner; an odd order from the most threads, the last environment and the last
    learner, so that two processes warming up at once reach different kernels first."""
    plan = [
        (threads, environment, learner)
        for threads in thread_counts
        for environment in ENVIRONMENTS
        for learner in learners.LEARNERS
    ]
    return plan[::-1] if order % 2 else plan


def warm_up(thread_counts: tuple[int, ...] = (1, 2), order: int = 0) -> float:
    """Every learner through what a study's updates do, in one environment of each domain,
    with each planner thread count: greedy policies and their exact evaluation before any
    data, an update on a demonstration, an update on the agent's own steps with feedback
    (restored from its saved state first, as an update process does), in the order of
    ``warm_up_plan(order)``. Returns the seconds it took."""
    started = time.perf_counter()
    rng = np.random.default_rng(0)
    envs = {name: domains.make(name) for name in ENVIRONMENTS}  # each made and planned once
    teachers = {name: Teacher(env, seed=0) for name, env in envs.items()}
    for threads, name, learner_name in warm_up_plan(order, thread_counts):
        with using_planner_threads(threads):
            _through_updates(envs[name], teachers[name], learner_name, rng)
    return time.perf_counter() - started


def _through_updates(
    env: Environment, teacher: Teacher, learner_name: str, rng: np.random.Generator
) -> None:
    """What every update does, in as few steps as the learner's schedule allows."""
    learner = make(learner_name, env, **learners.LEARNERS[learner_name].warm_up_settings)
    normalized_return(env, learner)
    for task in range(len(env.tasks)):
        steps = teacher.demonstration(task, _start(env, task))
        for state, action, next_state in steps[:6]:
            learner.record_demonstration(task, state, action, next_state)
    learner.update()
    learner = restore(env, learner.state_dict())
    for task in range(len(env.tasks)):
        state = _start(env, task)
        for action, feedback in ((1, 1), (4, -1), (STAY, 0)):
            next_state = env.step(state, action, rng)
            learner.record_agent_step(task, state, action, next_state, feedback)
            state = next_state
    learner.update()
    if isinstance(learner, PlannerLearner) and learner.dynamics_fit.compiled:
        # BAM's single dynamics step (where a step left the passes' layouts, which these
        # short fits do not meet): its compiled teacher gradient.
        learner.teacher_gradient(learner.teacher_data())
    normalized_return(env, learner)


def _start(env: Environment, task: int) -> int:
    return int(np.argmax(env.tasks[task].start))
