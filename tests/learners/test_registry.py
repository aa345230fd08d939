"""The learner registry (``server.names.LEARNER_REGISTRY``): its order is fixed (a learner's
position seeds its simulated agents' random streams), each entry names its class, and a
learner added in one line is picked up by every list and figure that names the learners."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from server import domains, learners, names
from server.learners.base import Learner
from server.learners.settings import Settings, setting
from server.names import LearnerInfo
from server.simulation import protocols
from tests.analysis.conftest import small_study, write_export

PUBLISHED_ORDER = ("bam", "model-based", "global-cost", "cloning")


def test_the_published_learners_keep_their_positions() -> None:
    assert tuple(learners.NAMES[: len(PUBLISHED_ORDER)]) == PUBLISHED_ORDER, (
        "the registry is append only: a learner's position seeds its simulated agents' random "
        "streams, so moving, removing or inserting one before another changes published curves"
    )


def test_each_learners_agents_are_seeded_by_its_position() -> None:
    env = domains.make("wall")
    for index, name in enumerate(learners.NAMES):
        job = protocols.Job("demonstrations", "wall", name, agent=2, rounds=1, seed=7)
        learner, _, _ = protocols.agent_streams(job, env)
        entropy = [7, protocols.environment_number("wall"), 2, protocols._OWN_STREAM, index]
        expected = np.random.SeedSequence(entropy).spawn(3)[0]
        assert learner.seed == protocols._seed(expected), name


def test_each_entry_is_its_learners_class() -> None:
    env = domains.make("wall")
    for name, info in names.LEARNER_REGISTRY.items():
        cls = learners.LEARNERS[name]
        assert cls.name == info.name == name
        assert f"{cls.__module__}:{cls.__qualname__}" == info.entry
        assert learners.make(name, env).name == name
    assert tuple(learners.LEARNERS) == tuple(learners.NAMES) == tuple(names.LEARNER_REGISTRY)
    assert dict(learners.DISPLAY_NAMES)["global-cost"] == "Model-Based IRL (global cost)"
    assert names.learner_names_prose() == "bam, model-based, global-cost, cloning"


def test_the_names_load_no_learning_stack_and_the_package_no_learner() -> None:
    def loaded(imports: str) -> str:
        code = f"import sys, {imports}; print(sorted({{'numpy', 'numba'}} & set(sys.modules)))"
        result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
        assert result.returncode == 0, result.stderr
        return result.stdout.strip()

    assert loaded("server.names") == "[]"
    # The package loads its base (NumPy), but no learner's module (numba's kernels) until a
    # learner is asked for.
    assert loaded("server.learners") == "['numpy']"


# -- a fifth learner, registered in one line ---------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class ToySettings(Settings):
    """The toy's one setting."""

    spread: float = setting(1.0, "Unused: the toy is uniform over the actions whatever it is.")


class ToyLearner(Learner):
    """Uniform over the actions, whatever it is taught."""

    name = "toy"
    settings_type = ToySettings

    def _fit(self) -> tuple[float, int]:
        return 0.0, 0

    def policy(self, task: int) -> np.ndarray:
        return np.full((self.env.num_states, self.env.num_actions), 1.0 / self.env.num_actions)

    def _parameters_state(self) -> dict[str, np.ndarray]:
        return {}

    def _load_parameters_state(self, state: dict[str, Any]) -> None:
        pass


TOY = LearnerInfo("toy", "Toy", "#000000", "v", f"{__name__}:ToyLearner")


@pytest.fixture
def toy(monkeypatch: pytest.MonkeyPatch) -> str:
    monkeypatch.setitem(names.LEARNER_REGISTRY, TOY.name, TOY)
    return TOY.name


def test_a_fifth_learner_is_in_every_list(toy: str) -> None:
    from analysis.names import LEARNERS, learner_display, order_learners
    from server.simulation.config import build_config

    assert learners.NAMES[-1] == toy and len(learners.NAMES) == 5
    assert learners.LEARNERS[toy] is ToyLearner
    assert learners.DISPLAY_NAMES[toy] == LEARNERS[toy] == learner_display(toy) == "Toy"
    assert order_learners(["toy", "cloning", "bam"], "bam") == ["bam", "cloning", "toy"]
    assert names.learner_names_prose().endswith(", cloning, toy")
    assert names.learner_names_prose(display=True).endswith(", Toy")
    config, _ = build_config("demonstrations", ["wall"], ["bam", toy], 1, 1, 0)
    assert config.learners == ("bam", toy)
    env = domains.make("wall")
    made = learners.make(toy, env, spread=2, **ToyLearner.warm_up_settings)
    restored = learners.restore(env, made.state_dict())
    assert isinstance(restored, ToyLearner) and restored.settings == ToySettings(spread=2)
    with pytest.raises(ValueError, match="spread must be a number, got 'wide'"):
        learners.make(toy, env, spread="wide")


def test_a_fifth_learner_leaves_the_others_seeds_alone(monkeypatch: pytest.MonkeyPatch) -> None:
    env = domains.make("wall")

    def seeds() -> dict[str, int]:
        jobs = (protocols.Job("demonstrations", "wall", n, 0, 1, 3) for n in learners.NAMES)
        return {job.learner: protocols.agent_streams(job, env)[0].seed for job in jobs}

    before = seeds()
    monkeypatch.setitem(names.LEARNER_REGISTRY, TOY.name, TOY)
    after = seeds()
    assert {name: after[name] for name in PUBLISHED_ORDER} == before
    assert after[TOY.name] not in before.values()


def test_a_fifth_learner_is_drawn_in_the_study_figures(toy: str, tmp_path: Path) -> None:
    from analysis.data import load_tables
    from analysis.plots import learning_curve_figure
    from analysis.results import analyze

    # The small study, its behavioural cloning sessions taught to the toy learner.
    study = [(*row[:3], toy if row[3] == "cloning" else row[3], *row[4:]) for row in small_study()]
    sessions, evaluations = load_tables(write_export(tmp_path / "export", study))
    figure = learning_curve_figure(analyze(sessions, evaluations), "episodes")
    lines = [line for line in figure.axes[0].get_lines() if line.get_label() == "Toy (n=4)"]
    assert len(lines) == 1 and lines[0].get_color() == TOY.colour


def test_a_fifth_learner_is_drawn_in_the_simulation_figures(toy: str, tmp_path: Path) -> None:
    from server.simulation.config import RunConfig
    from server.simulation.outputs import SummaryRow
    from server.simulation.plots import plot_curves

    config = RunConfig("demonstrations", ("wall",), ("bam", toy), agents=1, rounds=2, seed=0)
    summary = [
        SummaryRow("demonstrations", "wall", learner, round_, 1, 0.5, float("nan"), 1.0, 2.0, 0.0)
        for learner in config.learners
        for round_ in range(3)
    ]
    paths = plot_curves(config, summary, tmp_path / "figure")
    assert sorted(path.suffix for path in paths) == [".png", ".svg"]
    assert "Toy" in (tmp_path / "figure.svg").read_text(encoding="utf-8")
