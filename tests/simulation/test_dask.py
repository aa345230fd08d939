"""The Dask path (``--scheduler``) gives the same numbers as the local pool."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from server.commands.main import main
from server.simulation.config import ConfigError
from server.simulation.runner import DaskBackend
from tests.simulation.conftest import small_args, without_timing

distributed = pytest.importorskip("distributed")


def test_dask_cluster_gives_the_same_numbers(small_run: Path, tmp_path: Path) -> None:
    out = tmp_path / "dask"
    with distributed.LocalCluster(
        n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None
    ) as cluster:
        assert main(small_args(out, "feedback", "--scheduler", cluster.scheduler_address)) == 0
    for name in ("curves.csv", "summary.csv"):
        assert without_timing(out / name) == without_timing(small_run / name)
    report = (out / "report.md").read_text(encoding="utf-8")
    assert "Dask cluster" in report


def test_unreachable_scheduler_is_a_clear_error() -> None:
    with pytest.raises(ConfigError, match="cannot connect to the Dask scheduler"):
        DaskBackend("tcp://127.0.0.1:1", timeout=1)


def test_missing_dask_is_a_clear_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(sys.modules, "distributed", None)  # import fails as if not installed
    out = tmp_path / "out"
    assert main(small_args(out, "feedback", "--scheduler", "tcp://127.0.0.1:8786")) == 2
    assert "pip install 'bam-study[dask]'" in capsys.readouterr().err
    assert not out.exists()
