"""Finite-horizon planning: soft value iteration (the paper's equations (1)-(2)) with an exact
reverse-mode gradient, hard-max value iteration for the teacher, and exact expected returns.

The planner's Python side in one module: the passes, the transition operator whose layouts
they read (sorted out once per model and process), and the threads a pass splits over, whose
state is per process (the pool and its owner after a fork, whether OpenMP's threads run the
chunks, the scratch buffers, and ``run_pass``, through which every pass and compiled cost step
runs and which a benchmark wraps to count them). The compiled kernels are in ``_kernels``.

Conventions. Rewards are per state, ``reward[k, s]`` for task k (the paper's cost is
C = -reward). Q after ``horizon`` backups is the expected sum of ``horizon`` rewards:

    Q_1(s, a) = r(s)
    Q_t(s, a) = r(s) + sum_s' T(s, a, s') V_{t-1}(s')
    V_t(s)    = sum_a pi_t(a|s) Q_t(s, a),   pi_t proportional to exp(beta Q_t)

(a Boltzmann expectation, not log-sum-exp). Transitions are a dense (S, A, S) array or a
``SparseTransitions``; the gradient with respect to them comes back in the same form.

The reverse pass walks the backups once from t = horizon down to 1, so its cost is a small
constant times the forward pass whatever the number of parameters (the paper's forward-mode
Jacobians cost a factor of the number of parameters more).
"""

from __future__ import annotations

import functools
import math
import os
import threading
import weakref
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp

from server.domains.base import SparseTransitions, TransitionModel, check_finite
from server.learners import _kernels
from server.learners._kernels import ForwardLayout, ReverseLayout, TableGradient, Trace

# -- threads ----------------------------------------------------------------------------------
# A pass's tasks are independent, and the compiled kernels release the GIL, so a pass can split
# its tasks over threads. The numbers do not depend on the split (tested bit for bit). One
# thread unless set: processes that already fill the cores (a simulation's pool) gain nothing.
# The learners read no environment variable: whoever runs them sets the count (the server's
# update processes from its Settings, a simulation from its cores, a library user by calling
# ``set_planner_threads``).

_threads = 1
_pool: ThreadPoolExecutor | None = None
_pool_owner = (0, 0)  # (process id, threads) of the pool


def check_threads(value: object, source: str) -> int:
    """A positive whole number of planner threads; anything else is refused, naming where it
    came from."""
    try:
        threads = int(str(value).strip()) if isinstance(value, str) else value
    except ValueError:
        threads = None
    if isinstance(threads, bool) or not isinstance(threads, int | np.integer) or threads < 1:
        raise ValueError(f"{source} must be a positive integer, got {value!r}")
    return int(threads)


def set_planner_threads(threads: int) -> None:
    """Threads each planner pass of this process may use (at most one per task)."""
    global _threads
    _threads = check_threads(threads, "planner threads")


@contextmanager
def using_planner_threads(threads: int) -> Iterator[None]:
    """``threads`` for the passes run inside; the count before is restored after."""
    before = planner_threads()
    set_planner_threads(threads)
    try:
        yield
    finally:
        set_planner_threads(before)


def planner_threads() -> int:
    """This process's planner threads: as set, else 1."""
    return _threads


def task_chunks(num_tasks: int) -> tuple[tuple[int, int], ...]:
    """``num_tasks`` split into at most ``planner_threads()`` contiguous (first, last) runs."""
    return even_chunks(num_tasks, _threads)


@functools.lru_cache(maxsize=256)
def even_chunks(count: int, parts: int) -> tuple[tuple[int, int], ...]:
    """``range(count)`` split into at most ``parts`` contiguous (first, last) runs (kept: a
    learner's update splits the same tasks before each of its hundreds of passes)."""
    parts = max(1, min(parts, count))
    return tuple((i * count // parts, (i + 1) * count // parts) for i in range(parts))


# Chunks run on numba's OpenMP threads where that layer loads (GNU libgomp), else on a Python
# thread pool. GNU OpenMP does not survive a fork: a child forked after its parent ran a parallel
# loop uses the Python pool (the study server and simulations spawn their processes instead).
_openmp: bool | None = None  # None: not tried in this process yet


def compiled_threads() -> bool:
    """Whether this process splits passes over numba's OpenMP threads (tried on first use)."""
    global _openmp
    if _openmp is None:
        _openmp = _start_openmp()
    return _openmp


def _start_openmp() -> bool:
    import numba
    from numba.core import config

    if config.THREADING_LAYER == "default":  # type: ignore[attr-defined]
        # Not workqueue, numba's fallback: it hands over no faster than a Python pool, and
        # two threads launching at once abort the process.
        config.THREADING_LAYER = "omp"  # type: ignore[attr-defined]
    try:
        _kernels.probe_parallel(np.zeros(2))
    except (ValueError, ImportError, OSError):  # no OpenMP runtime here
        return False
    return bool(numba.threading_layer() == "omp")


def _forked() -> None:
    global _openmp
    if _openmp:
        _openmp = False


os.register_at_fork(after_in_child=_forked)


def run_pass(
    chunks: Sequence[tuple[int, int]],
    kernel: Callable[..., None],
    kernel_chunks: Callable[..., None] | None,
    arguments: tuple[Any, ...],
) -> None:
    """``kernel(*arguments, first, last)`` for every chunk of a pass: all of them in one call
    of ``kernel_chunks(*arguments, firsts, lasts)`` on OpenMP threads, or chunk by chunk on
    Python threads (``run_chunks``); one chunk runs here. Without ``kernel_chunks``, always on
    Python threads: for a kernel called once an update, whose thread hand-over costs nothing
    beside it, a parallel version would only be compiled (as long again as the kernel)."""
    if kernel_chunks is not None and len(chunks) > 1 and compiled_threads():
        firsts, lasts, threads = _bounds(tuple(chunks))
        # numba's thread count is per calling thread; set only when it changes (3 us a call).
        if getattr(_launches, "threads", None) != threads:
            import numba

            numba.set_num_threads(threads)  # type: ignore[attr-defined]
            _launches.threads = threads
        kernel_chunks(*arguments, firsts, lasts)
    else:
        run_chunks(lambda first, last: kernel(*arguments, first, last), chunks)


_launches = threading.local()


@functools.lru_cache(maxsize=64)
def _bounds(chunks: tuple[tuple[int, int], ...]) -> tuple[np.ndarray, np.ndarray, int]:
    """The chunks' firsts and lasts as the parallel kernels take them (which only read them),
    and the OpenMP threads they need."""
    from numba.core import config

    firsts = np.array([first for first, _ in chunks], dtype=np.int64)
    lasts = np.array([last for _, last in chunks], dtype=np.int64)
    return firsts, lasts, min(len(chunks), config.NUMBA_NUM_THREADS)  # type: ignore[attr-defined]


def run_chunks(work: Callable[[int, int], None], chunks: Sequence[tuple[int, int]]) -> None:
    """``work(first, last)`` for every chunk: the first in this thread, the others in the
    pool's, all finished (and their errors raised) on return."""
    if len(chunks) == 1:
        work(*chunks[0])
        return
    global _pool, _pool_owner
    # Sized by the chunks, not by planner_threads(), which another thread may have changed
    # since they were cut; a forked child inherits the pool object but not its threads.
    pid, needed = os.getpid(), len(chunks) - 1
    if _pool is None or _pool_owner[0] != pid or _pool_owner[1] < needed:
        _pool = ThreadPoolExecutor(needed, thread_name_prefix="planner")
        _pool_owner = (pid, needed)
    pending = [_pool.submit(work, *chunk) for chunk in chunks[1:]]
    try:
        work(*chunks[0])
    finally:
        for future in pending:
            future.result()


_scratch = threading.local()


def scratch(name: str, shape: tuple[int, ...], dtype: type = np.float64) -> np.ndarray:
    """This thread's working array ``name`` of ``shape``, its contents undefined, reused from
    call to call: fresh megabytes cost their first touch page by page (flip's kept dL/dQ, 2.5
    MB: a whole table's reverse pass on two threads took about 2.8 ms in fresh memory each
    time, 1.0 ms reused)."""
    size = math.prod(shape)
    buffers: dict[tuple[str, type], np.ndarray] = _scratch.__dict__.setdefault("buffers", {})
    buffer = buffers.get((name, dtype))
    if buffer is None or buffer.size < size:
        buffer = buffers[name, dtype] = np.empty(size, dtype)
    return buffer[:size].reshape(shape)


# The padding's probability in the passes' layouts (their source -1), in each precision.
ZERO = {dtype: np.zeros(1, dtype) for dtype in (np.float64, np.float32)}
# No kept terms, in each pass precision.
NO_TERMS: dict[type, np.ndarray] = {
    dtype: np.empty((0, 0, 0), dtype) for dtype in (np.float64, np.float32)
}
NO_ENTRIES = np.empty(0, dtype=np.int64)
NO_RUNS = np.empty((0, 5), dtype=np.int64)
# A reverse pass's transition gradient where it computes dL/dreward alone, in each precision.
NO_GRADIENT: dict[type, TableGradient] = {
    dtype: TableGradient(
        next_flat=NO_ENTRIES,  # not read without entries, nor the width
        width=0,
        entries=NO_ENTRIES,
        runs=NO_RUNS,
        slots=NO_ENTRIES,
        d_probs=np.empty(0, dtype),
        terms=NO_TERMS[dtype],
        kept_from=0,
        task_sums=NO_TERMS[dtype],
    )
    for dtype in (np.float64, np.float32)
}


@dataclass(frozen=True)
class _PassLayout:
    """Where a model's table entries go in the passes' layouts (``rows``, ``incoming``), for
    every theta whose moved entries are zero where ``nonzero`` says: the layouts depend on
    the table only through which entries are zero, so a learner's step fills them with its
    table's values (flip: 8 us) instead of sorting the table out again (46 us). Sources are
    flat entry indices, -1 for the reverse pass's padding (probability 0). With them, the
    model's moved entries sorted out (``TransitionOperator.distinct_entries``)."""

    nonzero: np.ndarray  # of the model's moved entries
    distinct: tuple[np.ndarray, np.ndarray, np.ndarray]
    shifts: np.ndarray
    shifted_source: np.ndarray
    shift_start: np.ndarray
    flat_rows: np.ndarray
    flat_next: np.ndarray
    flat_source: np.ndarray
    flat_start: np.ndarray
    dense_rows: np.ndarray
    dense_source: np.ndarray
    targets: np.ndarray
    sources: np.ndarray
    target_source: np.ndarray
    # The distinct moved entries that reverse passes sum in runs of states, and each one's
    # place in them (-1: summed alone), see ``_entry_runs``.
    entry_runs: np.ndarray
    entry_slots: np.ndarray

    @classmethod
    def of(cls, operator: TransitionOperator, nonzero: np.ndarray) -> _PassLayout:
        # The layouts of a table whose non-zero entries hold their own index + 1 (exact in
        # float64): the same kernels sort it out, and give each place's source entry.
        numbered = np.where(
            operator.probs_flat != 0.0, np.arange(1.0, operator.probs_flat.shape[0] + 1.0), 0.0
        )
        shape = (operator.next_flat, numbered, operator.width)
        sizes = (operator.num_states, operator.num_actions)
        shifts, shifted, shift_start, flat_rows, flat_next, flat, flat_start = _kernels.split_rows(
            *shape, *sizes
        )
        dense_rows, dense, targets, sources, incoming = _kernels.incoming(*shape, *sizes)

        def entry(numbers: np.ndarray) -> np.ndarray:
            return numbers.astype(np.int64) - 1

        distinct = operator._sort_out_entries()
        runs, slots = _entry_runs(
            shifts, entry(shifted), distinct[1], operator.num_states, operator.probs_flat.size
        )
        return cls(
            nonzero.copy(),
            distinct,
            shifts,
            entry(shifted),
            shift_start,
            flat_rows,
            flat_next,
            entry(flat),
            flat_start,
            dense_rows,
            entry(dense),
            targets,
            sources,
            entry(incoming),
            runs,
            slots,
        )

    def rows(self, probs_flat: np.ndarray) -> ForwardLayout:
        # Source -1: a shifted row's probability 0 (in the table's own precision).
        padded = np.concatenate((probs_flat, ZERO[probs_flat.dtype.type]))
        return ForwardLayout(
            self.shifts,
            padded[self.shifted_source],
            self.shift_start,
            self.flat_rows,
            self.flat_next,
            probs_flat[self.flat_source],
            self.flat_start,
        )

    def incoming(self, probs_flat: np.ndarray) -> ReverseLayout:
        padded = np.concatenate((probs_flat, ZERO[np.float64]))  # source -1: padding's 0
        return ReverseLayout(
            self.dense_rows,
            padded[self.dense_source],
            self.targets,
            self.sources,
            probs_flat[self.target_source],
        )


def _entry_runs(
    shifts: np.ndarray,
    shifted_source: np.ndarray,
    entries: np.ndarray,
    num_states: int,
    table_size: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Runs of the gradient ``entries`` that lie in one shifted row (one action, one offset):
    ``(a, d, lo, hi, at)``, the entries of states lo .. hi - 1 summed side by side from place
    ``at`` on, and each entry's place (-1: summed alone). A reverse pass then adds a backup's
    terms of a run as one SIMD loop over its states, not two gathers per entry; a run is kept
    where its entries are at least a quarter of its states (a gathered entry costs a few
    times a state's share of the loop). Navigation's moved entries all lie in runs (doorway:
    880 in 8 runs); gravity's and farming's are too scattered (flip: 30 of 480 in a shifted row)."""
    # Each table entry's place in the shifted rows (row * S + state), -1 outside them.
    place = np.full(table_size, -1, dtype=np.int64)
    groups, states = np.nonzero(shifted_source >= 0)
    place[shifted_source[groups, states]] = groups * num_states + states
    placed = place[entries]
    slots = np.full(entries.shape[0], -1, dtype=np.int64)
    runs = []
    at = 0
    for group in np.unique(placed[placed >= 0] // num_states):
        members = np.flatnonzero((placed >= 0) & (placed // num_states == group))
        states_of = placed[members] % num_states
        lo, hi = int(states_of.min()), int(states_of.max()) + 1
        if 4 * members.shape[0] < hi - lo:
            continue
        runs.append((int(shifts[group, 0]), int(shifts[group, 1]), lo, hi, at))
        slots[members] = at + states_of - lo
        at += hi - lo
    return np.array(runs, dtype=np.int64).reshape(-1, 5), slots


# Per transition model, its passes' layouts (``_PassLayout``).
_model_layouts: weakref.WeakKeyDictionary[TransitionModel, _PassLayout] = (
    weakref.WeakKeyDictionary()
)


class TransitionOperator:
    """A validated transition table in the padded sparse layout the compiled kernels use:
    rows ``s * A + a`` of ``width`` (next state, probability) entries. Dense (S, A, S) input
    becomes rows of width S."""

    def __init__(self, transitions: np.ndarray | SparseTransitions) -> None:
        self.dense_input = not isinstance(transitions, SparseTransitions)
        if not isinstance(transitions, SparseTransitions):
            probabilities = check_finite("transitions", transitions)
            if probabilities.ndim != 3 or probabilities.shape[0] != probabilities.shape[2]:
                raise ValueError(
                    "transitions must have shape (states, actions, states), "
                    f"got {probabilities.shape}"
                )
            num_states, num_actions, _ = probabilities.shape
            next_states = np.broadcast_to(
                np.arange(num_states), (num_states, num_actions, num_states)
            )
        else:
            next_states = np.asarray(transitions.next_states)
            probabilities = check_finite("transition probabilities", transitions.probabilities)
            if next_states.shape != probabilities.shape or next_states.ndim != 3:
                raise ValueError(
                    "sparse transitions: next_states and probabilities must share one "
                    "(S, A, M) shape"
                )
            num_states, num_actions, _ = next_states.shape
            if next_states.min() < 0 or next_states.max() >= num_states:
                raise ValueError("sparse transitions: a next state is out of range")
        if np.any(probabilities < 0.0):
            raise ValueError("transition probabilities must be non-negative")
        sums = probabilities.sum(axis=2)
        if not np.allclose(sums, 1.0, atol=1e-8):
            worst = np.unravel_index(np.argmax(np.abs(sums - 1.0)), sums.shape)
            raise ValueError(
                f"transition probabilities of (state, action) {tuple(int(i) for i in worst)} "
                f"sum to {sums[worst]:.6g}, not 1"
            )
        flat_probabilities = np.ascontiguousarray(probabilities, dtype=np.float64).reshape(-1)
        self._hold(
            next_states.shape,
            np.ascontiguousarray(next_states, dtype=np.int64).reshape(-1),
            flat_probabilities,
            # All entries' gradients unless narrowed with ``only_gradients_at``.
            np.arange(flat_probabilities.shape[0], dtype=np.int64),
            whole_table=True,
        )

    def _hold(
        self,
        shape: tuple[int, ...],
        next_flat: np.ndarray,
        probs_flat: np.ndarray,
        gradient_entries: np.ndarray,
        whole_table: bool,
    ) -> None:
        """Keep a checked table of ``shape`` (S, A, M), flattened to rows ``s * A + a``."""
        self.num_states, self.num_actions, self.width = (int(n) for n in shape)
        self.next_flat = next_flat
        self.probs_flat = probs_flat
        # The flat entries (``(s * A + a) * width + m``) whose gradient the reverse pass computes.
        self.gradient_entries = gradient_entries
        # Every entry's gradient (not narrowed to a model's entries): the reverse pass sums
        # the tasks' terms task by task, which the learners' narrowed passes do not (the last
        # bits of a sum over several tasks differ between the two orders).
        self.whole_table = whole_table
        # (gradient_entries, distinct ones, [copies; their originals]), see distinct_entries.
        self._distinct: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._matrix: sp.csr_matrix | None = None
        self._rows: ForwardLayout | None = None
        self._incoming: ReverseLayout | None = None
        # rows and incoming with their probabilities in float32, for float32 passes.
        self._single_rows: ForwardLayout | None = None
        self._single_incoming: ReverseLayout | None = None
        self._layout: _PassLayout | None = None

    @classmethod
    def build(cls, transitions: np.ndarray | SparseTransitions) -> TransitionOperator:
        return cls(transitions)

    @classmethod
    def of_model(cls, model: TransitionModel, theta: np.ndarray) -> TransitionOperator:
        """A learner's model space at ``theta``, with reverse passes narrowed to the entries
        theta moves (all the pull-back to theta reads). Built without the checks of arbitrary
        tables, which a model's table passes by construction: its next states are fixed and in
        range, and its rows are probability vectors for every finite theta (``probabilities``
        refuses any other; tests/domains checks the rows). A learner builds one per step."""
        operator = cls.__new__(cls)
        operator.dense_input = False
        operator._hold(
            model.next_states.shape,
            model.flat_next_states,
            model.probabilities(theta).reshape(-1),
            model.flat_parametric_entries,
            whole_table=False,
        )
        # A learner builds one per step: the model's entries and the passes' layouts are
        # sorted out once per pattern of zeros of the entries theta moves.
        nonzero = operator.probs_flat[model.flat_parametric_entries] != 0.0
        layout = _model_layouts.get(model)
        if layout is None or not (layout.nonzero == nonzero).all():
            layout = _PassLayout.of(operator, nonzero)
            _model_layouts[model] = layout
        operator._layout = layout
        operator._distinct = layout.distinct
        return operator

    def only_gradients_at(self, mask: np.ndarray) -> TransitionOperator:
        """Have reverse passes compute dL/dT only where ``mask`` (the table's shape) is true
        and return 0 elsewhere. A learner whose model space moves only some entries (flip:
        216 of 8000) skips the rest; the gradient at the kept entries is unchanged (to the
        last bit with one task; with several, the whole table sums each task's terms before
        adding the tasks' sums, the narrowed pass adds them as they come)."""
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != (self.num_states, self.num_actions, self.width):
            raise ValueError(
                f"gradient mask must have shape {(self.num_states, self.num_actions, self.width)}"
                f", got {mask.shape}"
            )
        self.gradient_entries = np.flatnonzero(mask.reshape(-1)).astype(np.int64)
        self.whole_table = False
        return self

    @property
    def distinct_entries(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The gradient entries with a (row, next state) of their own, and the others as
        (entry, the earlier entry it copies): entries of one row that lead to the same next
        state have the same terms in the same order, so the same gradient. Padding does (flip's
        whole table: 8000 entries, 3188 distinct); a model's moved entries do not."""
        if self._distinct is None or self._distinct[0] is not self.gradient_entries:
            self._distinct = self._sort_out_entries()
        return self._distinct[1], self._distinct[2][0], self._distinct[2][1]

    @property
    def layout(self) -> _PassLayout | None:
        """Where a model's table entries go in the passes' layouts (``of_model``'s tables; None
        for others)."""
        return self._layout

    def reverse_entries(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """What a reverse pass's transition gradient reads: ``distinct_entries`` and the runs
        of them it sums side by side with each one's place in them (``_entry_runs``; none
        where the table has no model's layout)."""
        entries, copies, originals = self.distinct_entries
        if self._layout is not None and entries is self._layout.distinct[1]:
            return entries, copies, originals, self._layout.entry_runs, self._layout.entry_slots
        return entries, copies, originals, NO_RUNS, NO_ENTRIES

    def _sort_out_entries(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(gradient entries, the distinct ones, [copies; their originals])."""
        entries = self.gradient_entries
        key = (entries // self.width) * self.num_states + self.next_flat[entries]
        _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
        copied = first[inverse] != np.arange(entries.shape[0])
        return (
            entries,
            np.ascontiguousarray(entries[np.sort(first)]),
            np.stack([entries[copied], entries[first[inverse[copied]]]]),
        )

    def _flat_table(self) -> tuple[np.ndarray, np.ndarray, int, int, int]:
        """The table as ``_kernels.split_rows`` and ``_kernels.incoming`` take it."""
        return self.next_flat, self.probs_flat, self.width, self.num_states, self.num_actions

    @property
    def rows(self) -> ForwardLayout:
        """The non-zero entries for forward passes, as ``_kernels.split_rows`` gives them
        (padding is most of the table in gravity and farming: 73% of flip's entries are zero).
        Built on first use: a learner's cost steps plan on one table many times."""
        if self._rows is None:
            if self._layout is not None:
                self._rows = self._layout.rows(self.probs_flat)
            else:
                self._rows = ForwardLayout(*_kernels.split_rows(*self._flat_table()))
        return self._rows

    @property
    def incoming(self) -> ReverseLayout:
        """The non-zero entries by next state for reverse passes, as ``_kernels.incoming``
        gives them, built on first use."""
        if self._incoming is None:
            if self._layout is not None:
                self._incoming = self._layout.incoming(self.probs_flat)
            else:
                self._incoming = ReverseLayout(*_kernels.incoming(*self._flat_table()))
        return self._incoming

    def rows_in(self, dtype: type) -> ForwardLayout:
        """``rows`` with their probabilities in ``dtype`` (float64: themselves; float32: a
        rounded copy, made once per table)."""
        if _check_pass_dtype(dtype) == np.float64:
            return self.rows
        if self._single_rows is None:
            if self._layout is not None and self._rows is None:
                # Gathered from the table rounded once (a learner's dynamics step plans on a
                # new table): the same numbers as the float64 rows rounded.
                self._single_rows = self._layout.rows(self.probs_flat.astype(np.float32))
            else:
                self._single_rows = _in_float32(self.rows)
        return self._single_rows

    def incoming_in(self, dtype: type) -> ReverseLayout:
        """``incoming`` in ``dtype``, as ``rows_in``; float32 reverse passes do not read it
        (they scatter through ``rows``), so it is made only when asked for."""
        if _check_pass_dtype(dtype) == np.float64:
            return self.incoming
        if self._single_incoming is None:
            self._single_incoming = _in_float32(self.incoming)
        return self._single_incoming

    def pass_layouts(self, dtype: type) -> tuple[ForwardLayout, ReverseLayout, bool]:
        """The table as the passes in ``dtype`` read it: ``rows``, ``incoming`` and whether
        reverse passes scatter through ``rows`` (float32) instead of summing by next state
        (float64; float32 passes get an empty ``incoming``)."""
        scatter = _check_pass_dtype(dtype) == np.float32
        incoming = NO_INCOMING_32 if scatter else self.incoming_in(dtype)
        return self.rows_in(dtype), incoming, scatter

    @property
    def matrix(self) -> sp.csr_matrix:
        """The table as a sparse (S*A, S) matrix (built on first use)."""
        if self._matrix is None:
            rows = np.repeat(np.arange(self.num_states * self.num_actions), self.width)
            self._matrix = sp.csr_matrix(
                (self.probs_flat, (rows, self.next_flat)),
                shape=(self.num_states * self.num_actions, self.num_states),
            )
        return self._matrix


def _check_pass_dtype(dtype: type) -> type:
    if dtype != np.float64 and dtype != np.float32:
        raise ValueError(f"passes run in float64 or float32, not {np.dtype(dtype).name}")
    return dtype


# A reverse pass's table by next state when it scatters through the forward layout instead
# (float32 passes): empty, of the types the kernel is compiled for.
NO_INCOMING_32 = ReverseLayout(
    np.empty((0, 0), dtype=np.int64),
    np.empty((0, 0), dtype=np.float32),
    NO_ENTRIES,
    NO_ENTRIES,
    np.empty(0, dtype=np.float32),
)


def _in_float32(layout: Any) -> Any:
    """A pass layout (``ForwardLayout``, ``ReverseLayout``) with its float arrays rounded to
    float32, the index arrays as they are."""
    return layout._make(a.astype(np.float32) if a.dtype == np.float64 else a for a in layout)


# The passes' precisions (the learners' setting ``planner_precision``).
PRECISIONS: dict[str, type] = {"float64": np.float64, "float32": np.float32}


@dataclass
class SoftPlan:
    """The result of a soft value iteration forward pass, kept for its reverse pass."""

    q_all: np.ndarray  # (K, S, A) after `horizon` backups
    operator: TransitionOperator
    beta: float
    horizon: int
    values: np.ndarray  # (horizon - 1, K, S): V_1 .. V_{horizon-1}
    # (horizon - 1, K, A, S), by action as the passes hold them: dV_t/dQ_t = pi (1 + beta (Q - V))
    jacobians_by_action: np.ndarray
    single_task: bool
    has_trace: bool  # the values and Jacobians were kept (keep_trace)

    @property
    def value_jacobians(self) -> np.ndarray:
        """dV_t/dQ_t of t = 1 .. horizon - 1, shape (horizon - 1, K, S, A) (a view)."""
        return self.jacobians_by_action.transpose(0, 1, 3, 2)

    @property
    def q(self) -> np.ndarray:
        """Q after `horizon` backups, with the caller's task dimension."""
        return self.q_all[0] if self.single_task else self.q_all

    def backward(
        self, d_q: np.ndarray, *, need_transitions: bool = True
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """From dL/dQ (same shape as ``q`` as returned), dL/dreward and dL/dtransitions.

        The transition gradient has the shape of the transitions given to the forward pass
        (dense (S, A, S) or the sparse (S, A, M) probabilities); ``need_transitions=False``
        skips it (a cost-only step).
        """
        d_q = np.asarray(d_q, dtype=np.float64)
        expected = self.q.shape
        if d_q.shape != expected:
            raise ValueError(f"dL/dQ must have shape {expected}, got {d_q.shape}")
        check_finite("dL/dQ", d_q)
        d_reward, d_transitions = self.checked_backward(
            d_q[None] if self.single_task else d_q, need_transitions=need_transitions
        )
        return (d_reward[0] if self.single_task else d_reward), d_transitions

    def checked_backward(
        self, g_q: np.ndarray, *, need_transitions: bool = True
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """``backward`` of a checked dL/dQ of every task, (tasks, S, A) in float64 (a learner's
        from its teacher data's likelihood, which refuses Q that is not finite), from a plan
        that kept its trace; dL/dreward is (tasks, S)."""
        if not self.has_trace:
            raise ValueError("this plan was computed without keep_trace; it has no reverse pass")
        op = self.operator
        dtype = self.q_all.dtype.type  # the forward pass's precision
        num_tasks = g_q.shape[0]
        if need_transitions:
            entries, copies, originals, runs, slots = op.reverse_entries()
        else:
            entries = copies = originals = slots = NO_ENTRIES
            runs = NO_RUNS
        d_reward = np.zeros((num_tasks, op.num_states), dtype)
        d_probs = np.zeros(op.next_flat.shape[0] if need_transitions else 0, dtype)
        # Split over threads, the first chunk's tasks add their transition gradient terms at
        # once and the later chunks' are kept and added after them, in the one-thread order:
        # worth it for the entries a learner's model moves (flip: 216 of 8000), whose order of
        # additions the learners' results depend on. A whole table's terms (flip: 8000 per
        # task and backup) are summed task by task instead and the tasks' sums added after
        # (the same bits for every split): kept terms took doorway twice as long as one
        # thread, and keeping dL/dQ to add the terms split by entries left flip's reverse pass
        # on two threads no faster than on one (its trace read across cores).
        chunks = task_chunks(num_tasks)
        by_task = op.whole_table and entries.shape[0] > 0
        split = len(chunks) > 1 and entries.shape[0] > 0 and not by_task
        kept_from = chunks[1][0] if split else num_tasks
        terms = scratch("terms", (num_tasks - kept_from, self.horizon - 1, entries.shape[0]), dtype)
        task_sums = (
            scratch("task sums", (num_tasks, 1, entries.shape[0]), dtype)
            if by_task
            else NO_TERMS[dtype]
        )
        gradient = TableGradient(
            op.next_flat, op.width, entries, runs, slots, d_probs, terms, kept_from, task_sums
        )
        run_pass(
            chunks,
            _kernels.soft_backward_tasks,
            _kernels.soft_backward_chunks,
            (
                *op.pass_layouts(dtype),
                Trace(self.q_all, self.values, self.jacobians_by_action),
                np.ascontiguousarray(g_q, dtype),
                self.horizon,
                d_reward,
                gradient,
            ),
        )
        if split:
            _kernels.add_terms(terms, entries, d_probs)
        if by_task:
            _kernels.add_terms(task_sums, entries, d_probs)
        d_probs[copies] = d_probs[originals]
        if dtype != np.float64:
            d_reward = d_reward.astype(np.float64)
            d_probs = d_probs.astype(np.float64)
        if not need_transitions:
            return d_reward, None
        # Dense input: width == S and the entries are T itself, so this is dL/dT.
        return d_reward, d_probs.reshape(op.num_states, op.num_actions, op.width)


def soft_value_iteration(
    transitions: np.ndarray | SparseTransitions | TransitionOperator,
    reward: np.ndarray,
    beta: float,
    horizon: int,
) -> np.ndarray:
    """Q after ``horizon`` soft backups; shape (S, A) for a reward (S,), (K, S, A) for (K, S)."""
    return soft_plan(transitions, reward, beta, horizon, keep_trace=False).q


def soft_plan(
    transitions: np.ndarray | SparseTransitions | TransitionOperator,
    reward: np.ndarray,
    beta: float,
    horizon: int,
    *,
    keep_trace: bool = True,
    precision: str = "float64",
) -> SoftPlan:
    """Forward pass of soft value iteration, keeping what the reverse pass needs.

    ``precision`` "float32" runs the pass (and its reverse pass) in single precision: Q, the
    trace and the gradients carry float32's 7 digits (Q to about 1e-6 relative, the gradients
    to about 1e-5), and the trace takes half the memory (flip's passes of an update: 498 ms in
    float64, 293 ms in float32, on an AVX-512 AMD EPYC)."""
    if precision not in PRECISIONS:
        raise ValueError(
            f"precision must be one of {', '.join(map(repr, PRECISIONS))}, got {precision!r}"
        )
    dtype = PRECISIONS[precision]
    operator = (
        transitions
        if isinstance(transitions, TransitionOperator)
        else TransitionOperator.build(transitions)
    )
    reward = check_finite("reward", reward)
    single_task = reward.ndim == 1
    rewards = reward[None] if single_task else reward
    if rewards.ndim != 2 or rewards.shape[1] != operator.num_states:
        raise ValueError(
            f"reward must have shape ({operator.num_states},) or (tasks, {operator.num_states}), "
            f"got {reward.shape}"
        )
    if not np.isfinite(beta) or beta <= 0:
        raise ValueError(f"beta must be a positive finite number, got {beta!r}")
    plan = checked_soft_plan(
        operator, rewards, float(beta), check_horizon(horizon), keep_trace=keep_trace, dtype=dtype
    )
    plan.single_task = single_task
    return plan


def checked_soft_plan(
    operator: TransitionOperator,
    rewards: np.ndarray,
    beta: float,
    horizon: int,
    *,
    keep_trace: bool = True,
    dtype: type = np.float64,
) -> SoftPlan:
    """``soft_plan`` of arguments checked where they were made: ``rewards`` (tasks, S) finite,
    beta positive and finite, the horizon a positive int, ``dtype`` one of the ``PRECISIONS``.
    A learner plans hundreds of times an update on rewards from its own bounded costs: they
    are checked where they are made, not around each pass (in wall, whose pass takes tens of
    microseconds, the checks were a share of the update that shows)."""
    num_tasks = rewards.shape[0]
    q: np.ndarray = np.empty((num_tasks, operator.num_states, operator.num_actions), dtype)
    # V_horizon and its Jacobian are never used (Q_horizon is the output).
    trace_len = horizon - 1 if keep_trace else 0
    values: np.ndarray = np.empty((trace_len, num_tasks, operator.num_states), dtype)
    jacobians: np.ndarray = np.empty(
        (trace_len, num_tasks, operator.num_actions, operator.num_states), dtype
    )
    rows = operator.rows_in(dtype)
    rewards = np.ascontiguousarray(rewards, dtype=dtype)

    run_pass(
        task_chunks(num_tasks),
        _kernels.soft_forward_tasks,
        _kernels.soft_forward_chunks,
        (rows, rewards, dtype(beta), horizon, bool(keep_trace), Trace(q, values, jacobians)),
    )
    return SoftPlan(
        q_all=q,
        operator=operator,
        beta=beta,
        horizon=horizon,
        values=values,
        jacobians_by_action=jacobians,
        single_task=False,
        has_trace=bool(keep_trace),
    )


def soft_value_iteration_backward(
    transitions: np.ndarray | SparseTransitions,
    reward: np.ndarray,
    beta: float,
    horizon: int,
    d_q: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Convenience: forward pass then reverse pass; returns (dL/dreward, dL/dtransitions)."""
    d_reward, d_transitions = soft_plan(transitions, reward, beta, horizon).backward(d_q)
    assert d_transitions is not None
    return d_reward, d_transitions


# -- the teacher's planner and exact evaluation ---------------------------------------------


def check_horizon(horizon: object) -> int:
    """A positive whole number of backups (rejects NaN, infinity, fractions and bools)."""
    if type(horizon) is int and horizon >= 1:  # the usual case, answered at once
        return horizon
    if isinstance(horizon, bool) or not isinstance(horizon, int | float | np.integer | np.floating):
        raise ValueError(f"horizon must be a positive integer, got {horizon!r}")
    if not np.isfinite(horizon) or int(horizon) != horizon or horizon < 1:
        raise ValueError(f"horizon must be a positive integer, got {horizon!r}")
    return int(horizon)


def hard_value_iteration(
    transitions: np.ndarray | SparseTransitions | TransitionOperator,
    reward: np.ndarray,
    horizon: int,
) -> np.ndarray:
    """Optimal finite-horizon Q after ``horizon`` backups with a hard max (same shapes as
    ``soft_value_iteration``)."""
    operator = (
        transitions
        if isinstance(transitions, TransitionOperator)
        else TransitionOperator.build(transitions)
    )
    reward = check_finite("reward", reward)
    rewards = reward[None] if reward.ndim == 1 else reward
    if rewards.ndim != 2 or rewards.shape[1] != operator.num_states:
        raise ValueError(
            f"reward must have shape ({operator.num_states},) or (tasks, {operator.num_states})"
        )
    horizon = check_horizon(horizon)
    q = _kernels.hard_backups(
        operator.next_flat,
        operator.probs_flat,
        operator.width,
        np.ascontiguousarray(rewards),
        int(horizon),
        operator.num_actions,
    )
    return q[0] if reward.ndim == 1 else q


def expected_return(
    transitions: np.ndarray | SparseTransitions | TransitionOperator,
    policy: np.ndarray,
    reward: np.ndarray,
    start: np.ndarray,
    horizon: int,
    after_transitions: bool = False,
) -> float:
    """Exact expected sum of ``horizon`` rewards of a stationary policy (S, A) of action
    probabilities (or (S,) actions) from the start distribution; no sampling. The rewards
    counted are r(s_0) ... r(s_{H-1}), or with ``after_transitions`` those of the states
    reached by the H transitions, r(s_1) ... r(s_H) (the paper authors' counting)."""
    operator = (
        transitions
        if isinstance(transitions, TransitionOperator)
        else TransitionOperator.build(transitions)
    )
    s, a = operator.num_states, operator.num_actions
    policy = np.asarray(policy)
    if policy.shape == (s,):
        actions = policy.astype(np.int64)
        if np.any((actions < 0) | (actions >= a)):
            raise ValueError("policy has an action out of range")
        policy = np.zeros((s, a))
        policy[np.arange(s), actions] = 1.0
    if policy.shape != (s, a):
        raise ValueError(f"policy must have shape ({s}, {a}) or ({s},), got {policy.shape}")
    check_finite("policy", policy)
    reward = check_finite("reward", reward)
    start = check_finite("start distribution", start)
    # P_pi = sum_a pi(s, a) T(s, a, .) as a sparse (S, S) matrix.
    weights = sp.csr_matrix(
        (policy.reshape(-1), (np.repeat(np.arange(s), a), np.arange(s * a))), shape=(s, s * a)
    )
    p_pi_t = (weights @ operator.matrix).T.tocsr()
    distribution = start.astype(np.float64)
    total = 0.0
    for _ in range(check_horizon(horizon)):
        if after_transitions:
            distribution = p_pi_t @ distribution
        total += float(distribution @ reward)
        if not after_transitions:
            distribution = p_pi_t @ distribution
    return total
