"""The learners' kernels compiled once per machine, and by every process that warms up at once.

Where numba's on-disk cache lacks the kernels (a new checkout, a new container, another CPU),
every process that warms up would compile them itself: a server's two update processes compiled
the same kernels side by side, a core each. Under ``kernels_compiled_once`` a kernel is compiled
by one process of the machine at a time, which writes it to the cache; a process that reaches a
kernel another is compiling waits for it, then loads what it wrote (numba reads the cache's index
on every load). Processes that warm up at once take turns in different orders (``warm_up_turn``
and ``warmup.warm_up_plan``), so that each compiles kernels the others have not reached: the
compile's wall time is shared by the cores, as far as the kernels' own order allows (one calls
another: the parallel kernels call the per-task ones they split).

A kernel's lock is a file beside the cache (``lock_folder``); a process that dies releases its
locks with it. The locks are taken after numba's own compiler lock, in the order in which kernels
call one another, so that neither threads of one process nor processes of one machine can wait
on each other in a ring.
"""

from __future__ import annotations

import fcntl
import importlib
import os
import pkgutil
from collections.abc import Callable, Iterable, Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import server.learners

TURN_FILE = "bam-warm-up-turns"


def lock_folder() -> Path:
    """Beside the kernels' cache: numba's own folder for server/learners (``__pycache__``, or
    NUMBA_CACHE_DIR), so processes that share a cache share the locks."""
    cache_dir = os.environ.get("NUMBA_CACHE_DIR")
    if cache_dir:
        return Path(cache_dir) / "bam-kernel-locks"
    return Path(server.learners.__file__).parent / "__pycache__" / "bam-kernel-locks"


def cached_kernels() -> list[Any]:
    """The learners' kernels that numba keeps in its on-disk cache (``cache=True``), each once."""
    from numba.core.registry import CPUDispatcher

    found: dict[int, Any] = {}
    for module in pkgutil.iter_modules(server.learners.__path__):
        namespace = vars(importlib.import_module(f"{server.learners.__name__}.{module.name}"))
        for value in namespace.values():
            if isinstance(value, CPUDispatcher) and value.stats.cache_path is not None:
                found.setdefault(id(value), value)
    return list(found.values())


@contextmanager
def kernels_compiled_once(kernels: Iterable[Any] | None = None) -> Iterator[None]:
    """While held, each of ``kernels`` (the learners' cached kernels by default) compiles a
    signature only under its machine-wide lock: the first process to need it compiles it and
    writes the cache, any other waits and loads it. Where the locks' folder cannot be written
    (a read-only install), nothing is held: each process compiles for itself."""
    folder = lock_folder()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        yield
        return
    with ExitStack() as undo:
        for kernel in cached_kernels() if kernels is None else kernels:
            original = kernel.__dict__.get("compile")
            kernel.compile = _under_lock(kernel.compile, folder / f"{_name(kernel)}.lock")
            undo.callback(_restore, kernel, original)
        yield


def _name(kernel: Any) -> str:
    return f"{kernel.py_func.__module__}.{kernel.py_func.__qualname__}"


def _restore(kernel: Any, original: Callable[..., Any] | None) -> None:
    if original is None:
        del kernel.compile  # the class's method again
    else:
        kernel.compile = original


def _under_lock(compile_: Callable[[Any], Any], path: Path) -> Callable[[Any], Any]:
    from numba.core.compiler_lock import global_compiler_lock

    def compile_signature(signature: Any) -> Any:
        # numba's lock first: a thread of this process holding a file lock never waits for the
        # compiler while another thread, holding the compiler, waits for that file.
        with global_compiler_lock, open(path, "a") as handle:
            fcntl.flock(handle, fcntl.LOCK_EX)
            return compile_(signature)  # loads from the cache what another process wrote

    return compile_signature


def warm_up_turn() -> int:
    """This process's turn among those that have warmed up with this cache (0, 1, 2, ...): a
    counter beside the cache, so that processes starting together take different orders.
    0 where the counter cannot be kept."""
    path = lock_folder() / TURN_FILE
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "a+") as handle:
            fcntl.flock(handle, fcntl.LOCK_EX)
            handle.seek(0)
            text = handle.read().strip()
            turn = int(text) if text.isdigit() else 0
            handle.seek(0)
            handle.truncate()
            handle.write(str(turn + 1))
            return turn
    except OSError:
        return 0


def warm_up_here() -> float:
    """This process warmed up (``warmup.warm_up``) in its turn's order, its kernels compiled
    once per machine: what an update process and a cluster worker do when they start. Returns
    the seconds it took."""
    from server.app.updates.warmup import warm_up

    with kernels_compiled_once():
        return warm_up(order=warm_up_turn())


def warm_up_in_processes(processes: int, warm: Callable[[], float] | None = None) -> float:
    """The warm-up (``warm``, by default ``warm_up_here``) in ``processes`` processes at once,
    this one and others spawned for it, each in its turn's order: where numba's cache lacks the
    kernels, a command that runs the learners in its own process compiles them on as many
    cores. Returns the seconds it took."""
    import time
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    warm = warm_up_here if warm is None else warm
    started = time.perf_counter()
    if processes <= 1:
        warm()
        return time.perf_counter() - started
    with ProcessPoolExecutor(processes - 1, mp_context=get_context("spawn")) as pool:
        others = [pool.submit(warm) for _ in range(processes - 1)]
        warm()
        for other in others:
            other.result()
    return time.perf_counter() - started
