"""The planner learners' updates on the authors' schedule learn what they learned before: two
updates of BAM and of model-based IRL, in every environment, from two rounds of the simulated
teacher's demonstrations, with the settings that reproduce the published runs
(``planner_precision = "float64"``, ``warm_share = 1``, ``compiled_steps = false``,
``compiled_dynamics_steps = false``), end at the
parameters (theta and the costs) and optimiser velocities recorded in ``update_reference.npz``
at commit 7463029. A change that makes updates cheaper (docs/benchmarks.md, "Where an
update's time goes") must keep them, or be a named setting.

Tolerance: 1e-12 relative plus 1e-12 absolute. The updates meet the reference to the last bit
(the compiled passes do the same operations in the same order); a change of the arithmetic an
update depends on compounds over its 400 steps far beyond it. So does the CPU: NumPy and
OpenBLAS choose their kernels by it, and on AVX-512 CPUs their AVX-512 kernels give other last
bits (an Intel Xeon's updates end up to 2.2 away in theta). The updates are therefore computed
in a process told to use the AVX2 kernels on every x86-64 CPU (``SAME_KERNELS``, as
docs/reproduction.md does for runs compared across machines), where the reference was
recorded.

Record again only for a change meant to alter what agents learn (then rerun the demonstrations
experiment, docs/reproduction.md): ``python -m tests.learners.test_same_updates --record``.
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from server import domains
from server.learners import make
from server.teacher import Teacher

REFERENCE = Path(__file__).with_name("update_reference.npz")
ROOT = Path(__file__).resolve().parents[2]
# NumPy's and OpenBLAS's AVX2 kernels, on any x86-64 CPU (set before NumPy is imported).
SAME_KERNELS = {"OPENBLAS_CORETYPE": "Haswell", "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL"}
LEARNERS = ("bam", "model-based")
ROUNDS = 2
FIELDS = ("theta", "costs", "theta_velocity", "cost_velocity")
TOLERANCE = 1e-12
SLOW = {"flip", "choices", "two-fields", "three-fields"}


def updated_parameters(env_name: str, learner_name: str) -> dict[str, np.ndarray]:
    """A learner's parameters after ``ROUNDS`` rounds of demonstrations, updated after each."""
    env = domains.make(env_name)
    learner = make(
        learner_name,
        env,
        seed=0,
        planner_precision="float64",
        warm_share=1.0,
        compiled_steps=False,
        compiled_dynamics_steps=False,
    )
    teacher = Teacher(env, seed=0)
    rng = np.random.default_rng(0)
    for _ in range(ROUNDS):
        for task in range(len(env.tasks)):
            for step in teacher.demonstration(task, env.sample_start(task, rng)):
                learner.record_demonstration(task, *step)
        learner.update()
    state = learner._parameters_state()  # type: ignore[attr-defined]
    return {field: np.asarray(state[field], dtype=np.float64) for field in FIELDS}


def compute(path: Path) -> None:
    """Every case's parameters into ``path`` (in this process)."""
    arrays = {}
    for env_name in domains.ENVIRONMENTS:
        for name in LEARNERS:
            for field, values in updated_parameters(env_name, name).items():
                arrays[f"{env_name}/{name}/{field}"] = values
    np.savez_compressed(path, **arrays)


def compute_apart(path: Path) -> None:
    """``compute`` in a new process on the AVX2 kernels (``SAME_KERNELS``)."""
    environment = dict(os.environ)
    if platform.machine().lower() in ("x86_64", "amd64"):
        environment.update(SAME_KERNELS)
    done = subprocess.run(
        [sys.executable, "-m", "tests.learners.test_same_updates", "--compute", str(path)],
        cwd=ROOT,
        env=environment,
        capture_output=True,
        text=True,
        timeout=1800,
    )
    assert done.returncode == 0, done.stderr


@pytest.fixture(scope="module")
def computed(tmp_path_factory: pytest.TempPathFactory) -> dict[str, np.ndarray]:
    path = tmp_path_factory.mktemp("same-updates") / "updates.npz"
    compute_apart(path)
    with np.load(path) as arrays:
        return {key: arrays[key] for key in arrays.files}


def cases() -> list[object]:
    return [
        pytest.param(env, name, marks=[pytest.mark.slow] if env in SLOW else [])
        for env in domains.ENVIRONMENTS
        for name in LEARNERS
    ]


@pytest.mark.parametrize(("env_name", "learner_name"), cases())
def test_an_update_learns_what_it_learned_before(
    env_name: str, learner_name: str, computed: dict[str, np.ndarray]
) -> None:
    with np.load(REFERENCE) as reference:
        expected = {field: reference[f"{env_name}/{learner_name}/{field}"] for field in FIELDS}
    got = {field: computed[f"{env_name}/{learner_name}/{field}"] for field in FIELDS}
    for field in FIELDS:
        assert got[field].shape == expected[field].shape, field
        np.testing.assert_allclose(
            got[field], expected[field], rtol=TOLERANCE, atol=TOLERANCE, err_msg=field
        )


def test_the_reference_moved_the_parameters() -> None:
    """The recorded updates did learn (a reference of untouched parameters would pass any
    learner that does nothing)."""
    with np.load(REFERENCE) as reference:
        for env_name in domains.ENVIRONMENTS:
            env = domains.make(env_name)
            for name in LEARNERS:
                costs = reference[f"{env_name}/{name}/costs"]
                theta = reference[f"{env_name}/{name}/theta"]
                assert np.abs(costs).max() > 1e-3
                assert np.abs(theta - env.model.initial_parameters()).max() > 1e-3


if __name__ == "__main__":
    if sys.argv[1:2] == ["--compute"] and len(sys.argv) == 3:
        compute(Path(sys.argv[2]))
    elif sys.argv[1:] == ["--record"]:
        compute_apart(REFERENCE)
    else:
        sys.exit("usage: python -m tests.learners.test_same_updates --record")
