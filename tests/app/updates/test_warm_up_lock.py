"""Each of the learners' kernels is compiled once per machine (server/app/updates/compiling.py):
where numba's cache lacks a kernel, the first process to need it compiles it and the others
wait and load it, and processes that warm up at once take different orders, so that they
compile different kernels side by side."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import server.app.updates.warmup as warmup
from server.app.updates import cluster, compiling, worker
from server.app.updates.compiling import (
    cached_kernels,
    kernels_compiled_once,
    lock_folder,
    warm_up_turn,
)
from server.learners import _kernels

# A cached kernel of its own (numba caches only functions defined in files), compiled by two
# processes that start it at the same moment (a barrier of files), its compile made 3 s longer
# so that each needs it while the other compiles, each reporting whether it compiled the
# kernel (a cache miss) or loaded it (a hit).
KERNEL = """
from numba import njit

@njit(cache=True)
def kernel(x):
    total = 0.0
    for i in range(x.shape[0]):
        total += x[i] * x[i] + 1.0
    return total
"""
RACE = """
import json, sys, time
from pathlib import Path
import numpy as np
sys.path.insert(0, sys.argv[1])
import toy_kernel
from server.app.updates.compiling import kernels_compiled_once

folder, me, guarded = Path(sys.argv[1]), sys.argv[2], sys.argv[3] == "guarded"
compile_now = toy_kernel.kernel.compile
def slow_compile(signature):  # a compile long enough for the other process to need it too
    time.sleep(3)
    return compile_now(signature)
toy_kernel.kernel.compile = slow_compile
(folder / f"ready-{me}").touch()
while len(list(folder.glob("ready-*"))) < 2:
    time.sleep(0.001)
if guarded:
    with kernels_compiled_once([toy_kernel.kernel]):
        toy_kernel.kernel(np.ones(3))
else:
    toy_kernel.kernel(np.ones(3))
stats = toy_kernel.kernel.stats
print(json.dumps({"misses": sum(stats.cache_misses.values()),
                  "hits": sum(stats.cache_hits.values())}))
"""


def race(folder: Path, guarded: bool) -> list[dict[str, int]]:
    folder.mkdir()
    (folder / "toy_kernel.py").write_text(textwrap.dedent(KERNEL))
    environment = {**os.environ, "NUMBA_CACHE_DIR": str(folder / "cache")}
    mode = "guarded" if guarded else "bare"
    processes = [
        subprocess.Popen(
            [sys.executable, "-c", RACE, str(folder), str(me), mode],
            stdout=subprocess.PIPE,
            env=environment,
            text=True,
        )
        for me in range(2)
    ]
    outputs = [process.communicate(timeout=120)[0] for process in processes]
    assert all(process.returncode == 0 for process in processes), outputs
    return [json.loads(output) for output in outputs]


def test_two_processes_needing_a_kernel_at_once_compile_it_once(tmp_path: Path) -> None:
    # Unguarded, both compile it (the race this module exists for) ...
    bare = race(tmp_path / "bare", guarded=False)
    assert [result["misses"] for result in bare] == [1, 1]
    # ... guarded, one compiles it and the other, having waited, loads what it wrote.
    guarded = race(tmp_path / "guarded", guarded=True)
    assert sorted(result["misses"] for result in guarded) == [0, 1]
    assert sorted(result["hits"] for result in guarded) == [0, 1]


def test_every_cached_learner_kernel_is_guarded_while_held_and_released_after(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    kernels = cached_kernels()
    assert _kernels.soft_forward_tasks in kernels and _kernels.cost_steps_tasks in kernels
    assert all(kernel.stats.cache_path is not None for kernel in kernels)
    with kernels_compiled_once():
        assert all("compile" in vars(kernel) for kernel in kernels)
    assert not any("compile" in vars(kernel) for kernel in kernels)  # the class's method again


def test_the_locks_sit_beside_the_kernels_cache(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("NUMBA_CACHE_DIR", "/some/cache")
    assert lock_folder().parent == Path("/some/cache")
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    assert lock_folder().parent.name == "__pycache__"
    assert lock_folder().parent.parent.name == "learners"


def test_processes_that_warm_up_take_turns_and_the_turns_alternate_the_order(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    assert [warm_up_turn() for _ in range(3)] == [0, 1, 2]
    first, second = warmup.warm_up_plan(0), warmup.warm_up_plan(1)
    assert sorted(first) == sorted(second) and len(set(first)) == len(first)
    assert first[0][0] == 1 and second[0][0] == 2  # one thread first, then the most threads
    assert first[0][2] != second[0][2] and first[0][1] != second[0][1]
    assert warmup.warm_up_plan(2) == first


def test_an_update_process_and_a_cluster_worker_warm_up_guarded_in_their_turns(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    seen: list[tuple[bool, int]] = []

    def warm_up(order: int = 0) -> float:
        seen.append(("compile" in vars(_kernels.soft_forward_tasks), order))
        return 0.0

    monkeypatch.setattr(warmup, "warm_up", warm_up)
    worker.worker_init(0, os.getppid())
    monkeypatch.setattr(cluster, "_warm", False)
    cluster.warm_this_process()
    assert seen == [(True, 0), (True, 1)]
    assert "compile" not in vars(_kernels.soft_forward_tasks)


def test_a_folder_that_cannot_be_written_guards_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    blocked = tmp_path / "file"
    blocked.write_text("not a folder")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(blocked / "cache"))
    with kernels_compiled_once():  # no OSError: the warm-up goes on, compiling for itself
        assert "compile" not in vars(_kernels.soft_forward_tasks)
    assert warm_up_turn() == 0


def record_turn() -> float:
    """A warm-up's stand-in for a spawned process: its pid and turn, in a file beside the cache."""
    (lock_folder() / f"turn-{os.getpid()}").write_text(str(warm_up_turn()))
    return 0.0


def test_a_command_warms_up_in_several_processes_each_in_its_turn(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))  # the spawned process inherits it
    compiling.warm_up_in_processes(2, record_turn)
    turns = {path.name: path.read_text() for path in lock_folder().glob("turn-*")}
    assert len(turns) == 2 and f"turn-{os.getpid()}" in turns  # this process and one other
    assert sorted(turns.values()) == ["0", "1"]
