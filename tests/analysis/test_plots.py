"""Learning curves: each session's latest value carried forward on a common grid, then the
mean and standard error per learner, a panel per environment."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from analysis.data import load_tables
from analysis.plots import learning_curve_figure, mean_and_standard_error, step_values
from analysis.results import analyze


def test_step_values_carry_the_latest_evaluation_forward() -> None:
    counts = np.array([2, 4, 4, 7])  # two updates at 4 episodes: the later one holds
    returns = np.array([0.1, 0.3, 0.5, 0.9])
    grid = np.array([0, 1, 2, 3, 4, 5, 7, 10])
    values = step_values(counts, returns, grid)
    assert np.isnan(values[:2]).all()  # before the first evaluation: no value
    assert values[2:].tolist() == [0.1, 0.1, 0.5, 0.5, 0.9, 0.9]


def test_mean_and_standard_error_over_the_sessions_with_a_value() -> None:
    values = np.array(
        [
            [np.nan, 0.2, 0.4],
            [np.nan, 0.6, 0.8],
            [0.5, 0.7, np.nan],
        ]
    )
    mean, se, n = mean_and_standard_error(values)
    assert n.tolist() == [1, 3, 2]
    assert mean[0] == pytest.approx(0.5) and np.isnan(se[0])  # one value: no error bar
    # [0.2, 0.6, 0.7]: mean 0.5, sample variance (0.09 + 0.01 + 0.04) / 2 = 0.07
    assert mean[1] == pytest.approx(0.5)
    assert se[1] == pytest.approx(math.sqrt(0.07 / 3))
    # [0.4, 0.8]: mean 0.6, sample variance 0.08
    assert se[2] == pytest.approx(math.sqrt(0.08 / 2))


def test_one_panel_per_environment_with_a_curve_per_learner(export: Path) -> None:
    sessions, evaluations = load_tables(export)
    analysis = analyze(sessions, evaluations)
    figure = learning_curve_figure(analysis, "episodes")
    panels = [ax for ax in figure.axes if ax.get_visible()]
    assert [ax.get_title() for ax in panels] == ["Two Rooms", "Doorway"]
    two_rooms = panels[0]
    labels = [line.get_label() for line in two_rooms.get_lines() if line.get_label()[0] != "_"]
    assert labels == ["BAM (n=4)", "Model-Based IRL (n=4)", "Behavioral Cloning (n=4)"]
    # BAM in Two Rooms after 10 episodes: every session's last value, 0.9.
    bam = two_rooms.get_lines()[len(analysis.thresholds)]  # after the threshold lines
    x, y = bam.get_data()
    assert y[list(x).index(10)] == pytest.approx(0.9)
    # Doorway's cloning curve counts only the 3 sessions with evaluations.
    doorway_labels = [line.get_label() for line in panels[1].get_lines()]
    assert "Behavioral Cloning (n=3)" in doorway_labels


def test_the_count_axes_have_whole_number_ticks(tmp_path: Path) -> None:
    """Few episodes (0 to 3) would otherwise get ticks at 0.5, 1.5, ..."""
    from .conftest import write_export

    curve = [(0, 0, 0.1), (1, 3, 0.4), (2, 5, 0.6), (3, 7, 0.9)]
    study = [
        ("a", "p1", "two-rooms", "bam", 0, curve),
        ("b", "p1", "two-rooms", "cloning", 1, curve[:3]),
    ]
    sessions, evaluations = load_tables(write_export(tmp_path / "export", study))
    analysis = analyze(sessions, evaluations)
    for x in ("episodes", "actions"):
        figure = learning_curve_figure(analysis, x)
        ticks = figure.axes[0].get_xticks()
        assert len(ticks) >= 2 and all(float(t).is_integer() for t in ticks), (x, ticks)


def test_the_legends_hide_no_data(export: Path) -> None:
    """Each panel's legend lies outside every panel (curves and error bands are drawn only
    inside them), below its own panel, and inside the figure."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    sessions, evaluations = load_tables(export)
    analysis = analyze(sessions, evaluations)
    for x in ("episodes", "actions"):
        figure = learning_curve_figure(analysis, x)
        FigureCanvasAgg(figure).draw()
        renderer = figure.canvas.get_renderer()  # type: ignore[attr-defined]
        panels = [ax for ax in figure.axes if ax.get_visible()]
        for ax in panels:
            legend = ax.get_legend()
            box = legend.get_window_extent(renderer)
            for other in panels:
                assert not box.overlaps(other.bbox), (x, ax.get_title(), other.get_title())
            assert box.y1 < ax.bbox.y0 and ax.bbox.x0 <= box.x0 and box.x1 <= ax.bbox.x1
            assert figure.bbox.contains(box.x0, box.y0) and figure.bbox.contains(box.x1, box.y1)
            # Below the axis's labels too.
            labels = ax.xaxis.get_tightbbox(renderer)
            assert not box.overlaps(labels), (x, ax.get_title())
