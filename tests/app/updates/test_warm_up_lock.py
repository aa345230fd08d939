"""The warm-up runs one process at a time on a machine (server/app/updates/compiling.py): where
numba's cache lacks the kernels, the first process compiles them and the others load them."""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

import pytest

import server.app.updates.warmup as warmup
from server.app.updates import cluster, worker
from server.app.updates.compiling import lock_path, one_warm_up_at_a_time


def held_elsewhere(path: Path) -> bool:
    """Does another holder have the lock? (A second open file, as another process's would be.)"""
    with open(path, "a") as probe:
        try:
            fcntl.flock(probe, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        fcntl.flock(probe, fcntl.LOCK_UN)
        return False


def test_the_lock_is_held_for_the_warm_up_and_released_after(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    path = lock_path()
    assert path.parent == tmp_path / "cache"  # beside the kernels' cache it guards
    with one_warm_up_at_a_time():
        assert held_elsewhere(path)
    assert not held_elsewhere(path)


def test_without_numba_cache_dir_the_lock_sits_in_the_learners_cache_folder(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    assert lock_path().parent.name == "__pycache__"
    assert lock_path().parent.parent.name == "learners"


def test_an_update_process_and_a_cluster_worker_warm_up_under_the_lock(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    seen: list[bool] = []

    def warm_up() -> float:
        seen.append(held_elsewhere(lock_path()))
        return 0.0

    monkeypatch.setattr(warmup, "warm_up", warm_up)
    worker.worker_init(0, os.getppid())
    monkeypatch.setattr(cluster, "_warm", False)
    cluster.warm_this_process()
    assert seen == [True, True]
    assert not held_elsewhere(lock_path())


def test_a_folder_that_cannot_be_written_holds_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    blocked = tmp_path / "file"
    blocked.write_text("not a folder")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(blocked / "cache"))
    with one_warm_up_at_a_time():
        pass  # no OSError: the warm-up goes on, compiling for itself
