"""Compiled inner loops of soft value iteration (the forward and the reverse pass) and the
learners' steps that call them (cost steps, theta steps, dynamics steps).

One module: the passes inline the exp and Boltzmann helpers (``inline="always"``), and the
steps inline the passes; numba's on-disk cache (``cache=True``) checks only the source file of
the function it compiled, so a helper edited in another module would leave stale compiled
passes in the cache, silently. The steps also compile in the likelihood of ``likelihoods.py``
(``data_log_likelihood_kernel``, ``step_advantages``), as the cloning steps do, and numba's
cache does not see an edit there: clear ``__pycache__`` after one.

Conventions (S states, A actions, K tasks, H the horizon, ``width`` entries per table row):

- **Arguments.** A kernel takes what its caller builds once as the named tuples below
  (``ForwardLayout``, ``ReverseLayout``, ``Trace``, ``TableGradient``, the teacher gradient's
  ``TeacherPasses``, the cost steps' ``CostCells``, ``TaskRecords``, ``TeacherModels``,
  ``StepSettings``, ``CostWorkspace``, ``CostState``), each field's shape beside it; numba
  types them as it types plain tuples. A kernel reads a field by name or unpacks the whole
  tuple in its fields' order, under their names. A parallel kernel (``*_chunks``) takes no
  tuple that holds a tuple: numba's parallel loops take tuples of arrays, not nested ones. Indexes are int64; the passes' arrays are in
  the passes' precision, float64 or float32 (the learners' setting ``planner_precision``),
  everything else float64. Outputs are written in place.
- **Rows.** The transitions are the padded sparse layout of ``SparseTransitions`` flattened to
  the table's rows ``s * A + a``, ``width`` entries each (``next_flat``, ``probs_flat``).
  Inside the passes Q's rows are held action by action, row ``a * S + s`` (``pass_row`` and
  ``table_row`` convert), as are the value Jacobians of the trace, ``jacobians[t, k, a, s]``
  (step t, task k): each state's work over its actions runs as one loop over states per
  action, which the compiler turns into SIMD code, each state's arithmetic in the order a loop
  over its actions would do it. Q itself comes out as ``q[k, s, a]``.
- **What the passes assume.** Every row of the table has a non-zero entry, and every index in
  a layout lies in its array (``split_rows`` and ``incoming`` build them; the gathers index
  unsigned, with no test for a negative index). A Boltzmann normaliser is at
  least 1 (the best action weighs exactly 1), so no division is checked for a zero divisor.
  Tasks are independent: a pass or a step computes tasks ``first .. last - 1``, and any split of
  the tasks over threads computes the same bits.
- **Sums.** A forward pass adds each row's terms level by level, those of one action that lead
  the same distance away as one shifted row (``split_rows``), the rest gathered. A reverse pass
  computes dL/dT only at the entries it is asked for (those the model space moves) and sums
  each next state's dL/dV from the dL/dQ of the rows that lead there: float64 passes in the
  table's order (``incoming``, gathered by next state), float32 passes scattered through the
  forward pass's layout (``_scatter_levels``: the same terms in another order, so other last
  bits).
- **Bit for bit.** Float64 passes and steps reproduce the published runs to the last bit
  (``tests/learners/test_same_updates.py``): an edit may change where a number is kept, not a
  float64 operation or its order (the five-action code, ``_boltzmann_five``, does the general
  loops' operations in their order). Nothing is compiled with ``fastmath``, and the passes and
  steps with NumPy's error model.
- **No literal arguments between kernels.** A kernel that calls a pass with a constant
  (``True``, ``0``) makes numba compile that pass again for the constant's literal type; such
  calls pass ``np.bool_(True)`` and ``np.int64(0)``, which take the pass compiled for every
  other caller (each pass compiled once per precision, not once per kind of caller).
- **Error codes.** A compiled step returns 0 or a code of the one block in ``likelihoods.py``
  (whose kernels return the first three, and which ``cloning`` shares); its caller raises it
  (``likelihoods.refuse`` for the likelihood's) or, for ``LAYOUT_CHANGED``, takes over:

  - ``BAD_INDEX`` (1): a task, state or action index out of range;
  - ``BAD_FEEDBACK`` (2): feedback other than +1, -1 or 0 (none);
  - ``IMPOSSIBLE_FEEDBACK`` (3): a feedback event of probability 0 under the feedback model;
  - ``GRADIENT_NOT_FINITE`` (9): a cost, theta, dynamics or cloning step's gradient;
  - ``LIKELIHOOD_NOT_FINITE`` (10): the teacher data's log-likelihood (Q is not finite);
  - ``IMPOSSIBLE_TRANSITION`` (11): an observed transition that no theta of the model space
    gives (``theta_steps``, ``dynamics_steps``, with the observed row);
  - ``LAYOUT_CHANGED`` (12): not an error; a dynamics step's table has a moved entry zero
    where the passes' layouts have it not, or the reverse (``dynamics_steps`` stops there).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.extending import intrinsic, overload

from server.domains.base import LEAST_PROBABILITY
from server.learners.likelihoods import (
    GRADIENT_NOT_FINITE,
    IMPOSSIBLE_TRANSITION,
    LAYOUT_CHANGED,
    LIKELIHOOD_NOT_FINITE,
    data_log_likelihood_kernel,
    step_advantages,
)

# -- the kernels' arguments -----------------------------------------------------------------------


class ForwardLayout(NamedTuple):
    """A table's non-zero entries for forward passes, level by level (``split_rows``): G
    shifted rows and F flat entries."""

    shifts: np.ndarray  # (G, 4): a shifted row's action a, offset d, its states lo .. hi - 1
    shifted_probability: np.ndarray  # (G, S): 0 at a state whose entry is not in the row
    shift_start: np.ndarray  # (levels + 1,): each level's first shifted row
    flat_rows: np.ndarray  # (F,): a flat entry's pass row a * S + s
    flat_next: np.ndarray  # (F,): its next state
    flat_probability: np.ndarray  # (F,)
    flat_start: np.ndarray  # (levels + 1,): each level's first flat entry


class ReverseLayout(NamedTuple):
    """A table's non-zero entries by next state for float64 reverse passes (``incoming``):
    the dense levels, then E flat entries. Empty where the reverse pass scatters."""

    dense_sources: np.ndarray  # (dense levels, S): the pass row of state s's entry there
    dense_probabilities: np.ndarray  # (dense levels, S): 0 where s has no such entry
    targets: np.ndarray  # (E,): a flat entry's next state
    sources: np.ndarray  # (E,): its pass row
    probabilities: np.ndarray  # (E,)


class Trace(NamedTuple):
    """What a forward pass writes, and its reverse pass reads (all but Q)."""

    q: np.ndarray  # (K, S, A): Q after H backups
    values: np.ndarray  # (H - 1, K, S): V_t of t = 1 .. H - 1; (0, K, S) without a trace
    jacobians: np.ndarray  # (H - 1, K, A, S): dV_t/dQ_t, by action


class TableGradient(NamedTuple):
    """Where a reverse pass computes dL/dT and how it adds it up (``soft_backward_tasks``):
    N entries, none (all empty) for a pass of dL/dreward alone."""

    next_flat: np.ndarray  # (S * A * width,): each table entry's next state, row s * A + a
    width: int
    entries: np.ndarray  # (N,): the flat table entries it computes, no two of one row and next
    runs: np.ndarray  # (R, 5): runs of them summed side by side, (a, d, lo, hi, at)
    slots: np.ndarray  # (N,): each entry's place in the runs (-1: summed alone), or empty
    d_probs: np.ndarray  # (S * A * width,): dL/dT, added into at ``entries``
    terms: np.ndarray  # (K - kept_from, H - 1, N): the terms kept for ``add_terms``, or empty
    kept_from: int  # the first task whose terms are kept (terms empty: none)
    task_sums: np.ndarray  # (K, 1, N): each task's sums (a whole table's gradient), or empty


class TeacherPasses(NamedTuple):
    """What the teacher data's gradient on a table plans on and writes (``teacher_gradient``),
    in the passes' precision but for the likelihood's arguments."""

    rows: ForwardLayout
    incoming: ReverseLayout
    scatter: bool  # the reverse pass sums dL/dV through ``rows`` (float32), not ``incoming``
    rewards: np.ndarray  # (K, S)
    beta: float
    horizon: int
    trace: Trace  # written
    likelihood: tuple[Any, ...]  # as ``data_log_likelihood_kernel`` takes them, but for Q
    d_reward: np.ndarray  # (K, S): dL/drewards, written
    gradient: TableGradient  # dL/dT at its distinct entries (no terms kept), written
    copies: np.ndarray  # the entries whose gradient is another's (``distinct_entries``)
    originals: np.ndarray  # the entries they copy


class CostCells(NamedTuple):
    """How the cost steps' tasks plan on rewards from costs per cell (C cells)."""

    data_row: np.ndarray  # (tasks,): a task's row in the passes' arrays, -1 without data
    plan_states: np.ndarray  # (P,): the states planned over, the passes' S
    state_cells: np.ndarray  # (S of the environment,): each state's cell
    num_features: int  # states per cell: cell c's are c * num_features + f
    cost_mask: np.ndarray  # (C,): 1 where a cell carries a cost, else 0


class TaskRecords(NamedTuple):
    """The teacher data by task with data: row r's demonstrations are ``demo_start[r] ..
    demo_start[r + 1] - 1``, in the data's order, ``demo_rows`` their places in the data;
    its agent steps likewise."""

    demo_rows: np.ndarray
    demo_start: np.ndarray  # (rows + 1,)
    demo_states: np.ndarray
    demo_actions: np.ndarray
    step_rows: np.ndarray
    step_start: np.ndarray  # (rows + 1,)
    step_states: np.ndarray
    step_actions: np.ndarray
    step_feedback: np.ndarray  # +1, -1 or 0 (none)


class TeacherModels(NamedTuple):
    """The action and feedback models' parameters (``likelihoods.ActionModel``,
    ``FeedbackModel``)."""

    beta: float
    normalized: bool
    variance_floor: float
    epsilon: float
    alpha: float
    mu_plus: float
    mu_minus: float


class StepSettings(NamedTuple):
    """A momentum step's settings (``clipped_momentum_step``)."""

    learning_rate: float
    momentum: float
    max_step: float
    clip_step: bool  # the step is clipped, not the velocity
    bound: float  # on each parameter's size (inf: none)


class CostWorkspace(NamedTuple):
    """The arrays the cost steps overwrite besides the trace, in the passes' precision, a row
    per task with data."""

    rewards: np.ndarray  # (rows, P)
    d_reward: np.ndarray  # (rows, P)
    d_q: np.ndarray  # (rows, P, A)


class CostState(NamedTuple):
    """What the cost steps step in place and report, a row per task of the environment."""

    costs: np.ndarray  # (tasks, C)
    velocity: np.ndarray  # (tasks, C): each task's optimiser's
    before: np.ndarray  # (tasks, C): the costs at the last step's start
    demo_values: np.ndarray  # (demonstrations,): their log-likelihoods there, the data's order
    step_values: np.ndarray  # (agent steps,): likewise
    codes: np.ndarray  # (tasks,): 0, or the error that stopped a task


# -- the exp: a polynomial that the compiler vectorises --------------------------------------------

# exp(x) = 2^k exp(r) with k = round(x / ln 2) and r = x - k ln 2 (ln 2 split in two parts so
# that r is exact to double precision; the constants are fdlibm's).
LN2_HI = 6.93147180369123816490e-01
LN2_LO = 1.90821492927058770002e-10
LOG2E = 1.4426950408889634
TWO_52_PLUS_BIAS = 4503599627371519.0  # 2^52 + 1023
EXPONENT_BIAS_BITS = np.int64(0x4330000000000000)  # the bits of 2^52

# Every environment has five actions (STAY, UP, DOWN, LEFT, RIGHT); the passes are compiled
# once more for exactly five, which lets the compiler unroll the per-state action loops
# (about 15% of a pass). Other counts (small test problems) take the general code.
FIVE_ACTIONS = 5


def _reinterpretation(name: str, source: types.Type, target: types.Type) -> Any:
    """An intrinsic ``name``: the ``target`` whose IEEE-754 bits are those of a ``source`` (a
    register move, no conversion)."""

    def typer(typingctx, x):  # type: ignore[no-untyped-def]
        def codegen(context, builder, sig, args):  # type: ignore[no-untyped-def]
            return builder.bitcast(args[0], context.get_value_type(target))

        return target(source), codegen

    typer.__name__ = typer.__qualname__ = name
    return intrinsic(typer)


_float_bits = _reinterpretation("_float_bits", types.float64, types.int64)
_bits_float = _reinterpretation("_bits_float", types.int64, types.float64)
_float32_bits = _reinterpretation("_float32_bits", types.float32, types.int32)
_bits_float32 = _reinterpretation("_bits_float32", types.int32, types.float32)


@intrinsic
def _fused_32(typingctx, a, b, c):  # type: ignore[no-untyped-def]
    """a * b + c of float32 numbers with one rounding (LLVM's fma: one instruction on CPUs
    with FMA, x86 since Haswell and Piledriver; elsewhere the C library's fmaf, the same
    result, slower)."""
    if not all(_is_float32(x) for x in (a, b, c)):
        return None

    def codegen(context, builder, sig, args):  # type: ignore[no-untyped-def]
        single = ir.FloatType()
        fma = builder.module.declare_intrinsic(
            "llvm.fma", [single], ir.FunctionType(single, [single, single, single])
        )
        return builder.call(fma, args)

    return types.float32(a, b, c), codegen


def multiply_add(a: float, b: float, c: float) -> float:
    """a * b + c in compiled code: in float32 (the float32 passes) with one rounding, a fused
    multiply-add (one instruction instead of two, and the nearer result); in float64 with two,
    as written, so that float64 passes keep their bits."""
    raise NotImplementedError("compiled code only")


@overload(multiply_add, inline="always")
def _multiply_add_of(a, b, c):  # type: ignore[no-untyped-def]
    if _is_float32(a) and _is_float32(b) and _is_float32(c):
        return lambda a, b, c: _fused_32(a, b, c)  # type: ignore[call-arg]  # (an intrinsic)
    return lambda a, b, c: a * b + c


# exp(r)'s Taylor coefficients 1/13!, 1/12!, ..., 1/1!, 1/0!, in Horner's order.
HORNER_FIRST = 1.0 / 479001600.0
HORNER = (
    1.0 / 39916800.0,
    1.0 / 3628800.0,
    1.0 / 362880.0,
    1.0 / 40320.0,
    1.0 / 5040.0,
    1.0 / 720.0,
    1.0 / 120.0,
    1.0 / 24.0,
    1.0 / 6.0,
    0.5,
    1.0,
    1.0,
)


# Float32 passes (the setting ``planner_precision = "float32"``): the same exp in single
# precision. ln 2 split as Cephes' expf has it, |r| <= ln(2) / 2, where the degree-7 Taylor
# polynomial's error (5e-9) is below float32's half unit in the last place (6e-8); x is clamped
# at -87 (exp(-87) = 1.6e-38 is the smallest weight, above float32's least normal number).
# Module-level float32 constants stay float32 in compiled code: a bare float literal would
# make every expression it touches float64.
def _single(x: float) -> float:
    """x rounded to a float32 constant (typed float for the type checker)."""
    return np.float32(x)  # type: ignore[return-value]


LN2_HI_32 = _single(0.693359375)
LN2_LO_32 = _single(-2.12194440e-4)
LOG2E_32 = _single(LOG2E)
HALF_32 = _single(0.5)
ZERO_32 = _single(0.0)
ONE_32 = _single(1.0)
EXP_FLOOR_32 = _single(-87.0)
TWO_23_PLUS_BIAS_32 = _single(12582912.0 + 127.0)  # 1.5 * 2^23 + 127
EXPONENT_BIAS_BITS_32 = np.int32(0x4B400000)  # the bits of 1.5 * 2^23
# 1/7!, 1/6!, ..., 1/1!, 1/0! (written out in the Horner steps below: a loop over a tuple,
# inlined through ``overload``, trips numba's SSA checks).
C7_32 = _single(1.0 / 5040.0)
C6_32 = _single(1.0 / 720.0)
C5_32 = _single(1.0 / 120.0)
C4_32 = _single(1.0 / 24.0)
C3_32 = _single(1.0 / 6.0)
C2_32 = _single(0.5)


@njit(inline="always", fastmath=False, error_model="numpy")
def _exp_reduce(x: float) -> tuple[float, float]:
    """k and r of exp(x) = 2^k exp(r), x clamped at -708."""
    v = max(x, -708.0)
    k = np.floor(v * LOG2E + 0.5)
    return k, (v - k * LN2_HI) - k * LN2_LO


@njit(inline="always", fastmath=False, error_model="numpy")
def _exp_scale(p: float, k: float) -> float:
    """p * 2^k. 2^k's bits, (k + 1023) << 52, without a float-to-int64 conversion (not a
    vector instruction before AVX-512): k + 1023 + 2^52 is exact, and its bits are
    EXPONENT_BIAS_BITS + k + 1023."""
    bits: int = _float_bits(k + TWO_52_PLUS_BIAS)  # type: ignore[call-arg]  # (numba intrinsics)
    return p * _bits_float((bits - EXPONENT_BIAS_BITS) << 52)  # type: ignore[call-arg]


@njit(inline="always", fastmath=False, error_model="numpy")
def _exp_reduce_32(x: float) -> tuple[float, float]:
    """``_exp_reduce`` in float32, x clamped at -87."""
    v = max(x, EXP_FLOOR_32)
    k = np.floor(v * LOG2E_32 + HALF_32)
    return k, (v - k * LN2_HI_32) - k * LN2_LO_32


@njit(inline="always", fastmath=False, error_model="numpy")
def _exp_scale_32(p: float, k: float) -> float:
    """``_exp_scale`` in float32: k + 127 + 1.5 * 2^23 is exact, and its bits are
    EXPONENT_BIAS_BITS_32 + k + 127."""
    bits: int = _float32_bits(k + TWO_23_PLUS_BIAS_32)  # type: ignore[call-arg]
    return p * _bits_float32((bits - EXPONENT_BIAS_BITS_32) << 23)  # type: ignore[call-arg]


@njit(inline="always", fastmath=False, error_model="numpy")
def _exp_one_32(x: float) -> float:
    """exp(x) for float32 x <= 0, within 2 units in the last place of float32's exp."""
    k, r = _exp_reduce_32(x)
    return _exp_scale_32(_horner_32(r), k)


@njit(inline="always", fastmath=False, error_model="numpy")
def _horner_32(r: float) -> float:
    """exp(r)'s degree-7 Taylor polynomial in float32, Horner's order."""
    p = multiply_add(C7_32, r, C6_32)
    p = multiply_add(p, r, C5_32)
    p = multiply_add(p, r, C4_32)
    p = multiply_add(p, r, C3_32)
    p = multiply_add(p, r, C2_32)
    p = multiply_add(p, r, ONE_32)
    return multiply_add(p, r, ONE_32)


@njit(inline="always", fastmath=False, error_model="numpy")
def _exp_five_32(
    x0: float, x1: float, x2: float, x3: float, x4: float
) -> tuple[float, float, float, float, float]:
    """``_exp_five_64`` in float32."""
    k0, r0 = _exp_reduce_32(x0)
    k1, r1 = _exp_reduce_32(x1)
    k2, r2 = _exp_reduce_32(x2)
    k3, r3 = _exp_reduce_32(x3)
    k4, r4 = _exp_reduce_32(x4)
    return (
        _exp_scale_32(_horner_32(r0), k0),
        _exp_scale_32(_horner_32(r1), k1),
        _exp_scale_32(_horner_32(r2), k2),
        _exp_scale_32(_horner_32(r3), k3),
        _exp_scale_32(_horner_32(r4), k4),
    )


def _is_float32(x: Any) -> bool:
    return isinstance(x, types.Float) and x.bitwidth == 32


def exp_nonpositive_one(x: float) -> float:
    """exp(x) for x <= 0 in compiled code, in the precision of x (``_exp_one_64``,
    ``_exp_one_32``)."""
    raise NotImplementedError("compiled code only")


@overload(exp_nonpositive_one, inline="always")
def _exp_one_of(x: float):  # type: ignore[no-untyped-def]  # (annotated as the implementations are)
    return (_exp_one_32 if _is_float32(x) else _exp_one_64).py_func


def exp_nonpositive_five(
    x0: float, x1: float, x2: float, x3: float, x4: float
) -> tuple[float, float, float, float, float]:
    """Five exps of x <= 0 in compiled code, in the precision of x0 (``_exp_five_64``,
    ``_exp_five_32``)."""
    raise NotImplementedError("compiled code only")


@overload(exp_nonpositive_five, inline="always")
def _exp_five_of(x0: float, x1: float, x2: float, x3: float, x4: float):  # type: ignore[no-untyped-def]
    return (_exp_five_32 if _is_float32(x0) else _exp_five_64).py_func


def zero_as(x: float) -> float:
    """0 in the precision of x, in compiled code (a bare 0.0 is float64 there, and makes
    float32 arithmetic it touches float64)."""
    raise NotImplementedError("compiled code only")


@overload(zero_as, inline="always")
def _zero_as_of(x):  # type: ignore[no-untyped-def]
    if _is_float32(x):
        return lambda x: ZERO_32
    return lambda x: 0.0


def one_as(x: float) -> float:
    """1 in the precision of x, in compiled code (see ``zero_as``)."""
    raise NotImplementedError("compiled code only")


@overload(one_as, inline="always")
def _one_as_of(x):  # type: ignore[no-untyped-def]
    if _is_float32(x):
        return lambda x: ONE_32
    return lambda x: 1.0


@njit(inline="always", fastmath=False, error_model="numpy")
def _exp_one_64(x: float) -> float:
    """exp(x) for x <= 0, within 4e-16 relative of ``np.exp`` (x below -708, where exp
    underflows to subnormals, is taken as -708: a weight of 3e-308 instead of less). exp(0) is
    exactly 1.

    Branch-free so that loops calling it vectorise: |r| <= ln(2) / 2, where the degree-13
    Taylor polynomial's error is below 1e-17, and 2^k is built from its IEEE-754 bits."""
    k, r = _exp_reduce(x)
    p = HORNER_FIRST
    for step in range(12):  # each coefficient by a constant index (see _horner_steps_64)
        p = p * r + HORNER[step]
    return _exp_scale(p, k)


@njit(inline="always", fastmath=False, error_model="numpy")
def _horner_steps_64(
    p0: float,
    p1: float,
    p2: float,
    p3: float,
    p4: float,
    r0: float,
    r1: float,
    r2: float,
    r3: float,
    r4: float,
    c: float,
) -> tuple[float, float, float, float, float]:
    """One Horner step of five polynomials side by side: p * r + c of each."""
    return p0 * r0 + c, p1 * r1 + c, p2 * r2 + c, p3 * r3 + c, p4 * r4 + c


@njit(inline="always", fastmath=False, error_model="numpy")
def _exp_five_64(
    x0: float, x1: float, x2: float, x3: float, x4: float
) -> tuple[float, float, float, float, float]:
    """``_exp_one_64`` of five numbers, the same operations on each, their Horner steps
    interleaved: the five chains of dependent steps then run side by side (one after the
    other, each step waited on the one before; a forward pass spent 60% of its time there)."""
    k0, r0 = _exp_reduce(x0)
    k1, r1 = _exp_reduce(x1)
    k2, r2 = _exp_reduce(x2)
    k3, r3 = _exp_reduce(x3)
    k4, r4 = _exp_reduce(x4)
    p0 = p1 = p2 = p3 = p4 = HORNER_FIRST
    # The steps written out, not a loop over HORNER: such a loop, inlined through
    # ``exp_nonpositive_five``'s overload, trips numba's SSA checks (a warning at compile time).
    p0, p1, p2, p3, p4 = _horner_steps_64(p0, p1, p2, p3, p4, r0, r1, r2, r3, r4, HORNER[0])
    p0, p1, p2, p3, p4 = _horner_steps_64(p0, p1, p2, p3, p4, r0, r1, r2, r3, r4, HORNER[1])
    p0, p1, p2, p3, p4 = _horner_steps_64(p0, p1, p2, p3, p4, r0, r1, r2, r3, r4, HORNER[2])
    p0, p1, p2, p3, p4 = _horner_steps_64(p0, p1, p2, p3, p4, r0, r1, r2, r3, r4, HORNER[3])
    p0, p1, p2, p3, p4 = _horner_steps_64(p0, p1, p2, p3, p4, r0, r1, r2, r3, r4, HORNER[4])
    p0, p1, p2, p3, p4 = _horner_steps_64(p0, p1, p2, p3, p4, r0, r1, r2, r3, r4, HORNER[5])
    p0, p1, p2, p3, p4 = _horner_steps_64(p0, p1, p2, p3, p4, r0, r1, r2, r3, r4, HORNER[6])
    p0, p1, p2, p3, p4 = _horner_steps_64(p0, p1, p2, p3, p4, r0, r1, r2, r3, r4, HORNER[7])
    p0, p1, p2, p3, p4 = _horner_steps_64(p0, p1, p2, p3, p4, r0, r1, r2, r3, r4, HORNER[8])
    p0, p1, p2, p3, p4 = _horner_steps_64(p0, p1, p2, p3, p4, r0, r1, r2, r3, r4, HORNER[9])
    p0, p1, p2, p3, p4 = _horner_steps_64(p0, p1, p2, p3, p4, r0, r1, r2, r3, r4, HORNER[10])
    p0, p1, p2, p3, p4 = _horner_steps_64(p0, p1, p2, p3, p4, r0, r1, r2, r3, r4, HORNER[11])
    return (
        _exp_scale(p0, k0),
        _exp_scale(p1, k1),
        _exp_scale(p2, k2),
        _exp_scale(p3, k3),
        _exp_scale(p4, k4),
    )


@njit(cache=True, fastmath=False, error_model="numpy")
def exp_nonpositive(x: np.ndarray, out: np.ndarray) -> None:
    """out[i] = exp(x[i]) for x[i] <= 0, as ``exp_nonpositive_one``."""
    for i in range(x.shape[0]):
        out[i] = exp_nonpositive_one(x[i])


# -- rows and layouts: the table's and the passes' -------------------------------------------------


@njit(inline="always")
def pass_row(row: int, num_states: int, num_actions: int) -> int:
    """The passes' row ``a * S + s`` of the table's row ``s * A + a``."""
    return (row % num_actions) * num_states + row // num_actions


@njit(inline="always")
def table_row(row: int, num_states: int, num_actions: int) -> int:
    """The table's row ``s * A + a`` of the passes' row ``a * S + s``."""
    return (row % num_states) * num_actions + row // num_states


@njit(cache=True)
def split_rows(
    next_flat: np.ndarray, probs_flat: np.ndarray, width: int, num_states: int, num_actions: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The table's non-zero entries for forward passes, by level (every row's first entry,
    then every second one, and so on; a row of probabilities has at least one), each level's
    entries as shifted rows and flat triples. The table comes in its flat layout (row
    ``s * A + a``); the passes' rows are ``a * S + s``.

    A shifted row is one action's entries of a level that lead from state s to s + d for one
    offset d: ``shifts[g] = (a, d, lo, hi)`` and ``shifted_probability[g, s]``, the states
    lo .. hi - 1 spanning them, 0 where a state's entry is not in it. A pass adds it as one loop
    over states, which the compiler turns into SIMD code (a next state's value read at a fixed
    offset, not gathered); adding 0 * V leaves a sum as it is. Grid worlds' moves are a few
    offsets per action (flip: 1910 of its 2000 first entries in 9 shifted rows), so a forward
    pass gathers only the rest: the flat triples, row ``rows[e]`` adds ``probability[e]`` times
    the value of ``next[e]``. ``shift_start`` and ``flat_start`` give each level's groups.
    Every row's terms are added in its own order, each level after the one before. Its four
    sweeps of the table (entries per row, each level's entries, their offsets, the groups)
    share the counts of the one before."""
    num_rows = num_states * num_actions
    counts = np.zeros(num_rows, dtype=np.int64)
    for i in range(num_rows):  # the pass's row i is the table's row s * A + a
        base = table_row(i, num_states, num_actions) * width
        for m in range(width):
            if probs_flat[base + m] != 0.0:
                counts[i] += 1
    levels = 0
    for i in range(num_rows):
        levels = max(levels, counts[i])
    # Each row's entry of each level (its flat index), -1 past its last.
    entry = np.full((levels, num_rows), -1, dtype=np.int64)
    for i in range(num_rows):
        base = table_row(i, num_states, num_actions) * width
        seen = 0
        for m in range(width):
            if probs_flat[base + m] != 0.0:
                entry[seen, i] = base + m
                seen += 1
    span = 2 * num_states - 1  # offsets -(S - 1) .. S - 1
    # An offset's shifted row pays for a loop over its states; a flat entry costs a few times
    # a state's share of that loop: shifted when it carries a sixteenth of the states or more.
    shifted = np.zeros((levels, num_actions, span), dtype=np.bool_)
    group_count = 0
    flat_count = 0
    for level in range(levels):
        offsets = np.zeros((num_actions, span), dtype=np.int64)
        for i in range(num_rows):
            j = entry[level, i]
            if j >= 0:
                offsets[i // num_states, next_flat[j] - i % num_states + num_states - 1] += 1
        for a in range(num_actions):
            for o in range(span):
                if offsets[a, o] > 0:
                    if 16 * offsets[a, o] >= num_states:
                        shifted[level, a, o] = True
                        group_count += 1
                    else:
                        flat_count += offsets[a, o]
    shifts = np.empty((group_count, 4), dtype=np.int64)
    shifted_probability = np.zeros((group_count, num_states), dtype=probs_flat.dtype)
    shift_start = np.zeros(levels + 1, dtype=np.int64)
    flat_rows = np.empty(flat_count, dtype=np.int64)
    flat_next = np.empty(flat_count, dtype=np.int64)
    flat_probability = np.empty(flat_count, dtype=probs_flat.dtype)
    flat_start = np.zeros(levels + 1, dtype=np.int64)
    g = 0
    e = 0
    for level in range(levels):
        for a in range(num_actions):
            for o in range(span):
                if not shifted[level, a, o]:
                    continue
                lo, hi = num_states, 0
                for s in range(num_states):
                    j = entry[level, a * num_states + s]
                    if j >= 0 and next_flat[j] - s + num_states - 1 == o:
                        shifted_probability[g, s] = probs_flat[j]
                        lo = min(lo, s)
                        hi = max(hi, s + 1)
                shifts[g, 0] = a
                shifts[g, 1] = o - (num_states - 1)
                shifts[g, 2] = lo
                shifts[g, 3] = hi
                g += 1
        for i in range(num_rows):
            j = entry[level, i]
            if j >= 0:
                s = i % num_states
                if not shifted[level, i // num_states, next_flat[j] - s + num_states - 1]:
                    flat_rows[e] = i
                    flat_next[e] = next_flat[j]
                    flat_probability[e] = probs_flat[j]
                    e += 1
        shift_start[level + 1] = g
        flat_start[level + 1] = e
    return (
        shifts,
        shifted_probability,
        shift_start,
        flat_rows,
        flat_next,
        flat_probability,
        flat_start,
    )


# -- the passes: forward (with its trace) and reverse, one thread ----------------------------------


@njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def soft_forward_tasks(
    rows: ForwardLayout,
    rewards: np.ndarray,
    beta: float,
    horizon: int,
    keep_trace: bool,
    trace: Trace,
    first: int,
    last: int,
) -> None:
    """Tasks ``first .. last - 1`` of a forward pass on rewards (K, S), written into
    ``trace.q`` and, with ``keep_trace``, the values V_t (``values[t - 1, k, s]``) and value
    Jacobians dV_t/dQ_t (``jacobians[t - 1, k, a, s]``, by action) of t = 1 .. horizon - 1 that
    the reverse pass needs. The table is given by its non-zero entries as ``split_rows``
    returns them. Tasks are independent: any split of them over threads (the kernel releases
    the GIL) computes the same bits."""
    num_actions = trace.q.shape[2]
    if num_actions == FIVE_ACTIONS:
        _soft_forward(rows, rewards, beta, horizon, keep_trace, trace, first, last, FIVE_ACTIONS)
    else:
        _soft_forward(rows, rewards, beta, horizon, keep_trace, trace, first, last, num_actions)


@njit(inline="always", fastmath=False, error_model="numpy")
def _soft_forward(
    layout: ForwardLayout,
    rewards: np.ndarray,
    beta: float,
    horizon: int,
    keep_trace: bool,
    trace: Trace,
    first: int,
    last: int,
    num_actions: int,
) -> None:
    shifts, shifted_probability, shift_start, flat_rows, flat_next, flat_probability, flat_start = (
        layout
    )
    q, values, jacobians = trace
    num_states = rewards.shape[1]
    n = num_states * num_actions
    dtype = rewards.dtype  # float64, or float32 passes
    previous = np.zeros(num_states, dtype)
    rows = np.empty(n, dtype)  # Q_t, row a * S + s
    weights = np.empty(n, dtype)
    total = np.empty(num_states, dtype)
    value = np.empty(num_states, dtype)
    one = one_as(beta)
    shifted_flat = shifted_probability.reshape(-1)
    for k in range(first, last):
        reward = rewards[k]
        for s in range(num_states):
            previous[s] = 0.0
        for t in range(horizon):
            if t == 0:
                for a in range(num_actions):
                    for s in range(num_states):
                        rows[a * num_states + s] = reward[s]
            else:
                # r + each entry's term in row order (see ``split_rows``).
                for a in range(num_actions):
                    for s in range(num_states):
                        rows[a * num_states + s] = reward[s]
                for level in range(shift_start.shape[0] - 1):
                    for g in range(shift_start[level], shift_start[level + 1]):
                        a, d, lo, hi = shifts[g, 0], shifts[g, 1], shifts[g, 2], shifts[g, 3]
                        # Unsigned indices: no test for a negative one (counted from the end),
                        # which kept the loop scalar; each lies in its array (split_rows).
                        row = np.uint64(a * num_states + lo)
                        cell = np.uint64(g * num_states + lo)
                        source = np.uint64(lo + d)
                        for j in range(np.uint64(hi - lo)):
                            rows[row + j] = multiply_add(
                                shifted_flat[cell + j], previous[source + j], rows[row + j]
                            )
                    # Unsigned here too (each index lies in its array): with the tests for
                    # negative indices, flip's pass took a tenth longer.
                    for e in range(np.uint64(flat_start[level]), np.uint64(flat_start[level + 1])):
                        i = np.uint64(flat_rows[e])
                        rows[i] = multiply_add(
                            flat_probability[e], previous[np.uint64(flat_next[e])], rows[i]
                        )
            if t == horizon - 1:
                # Q_horizon is the output; its Boltzmann value is never used.
                for s in range(num_states):
                    for a in range(num_actions):
                        q[k, s, a] = rows[a * num_states + s]
                break
            # V_t into its own array, then copied to ``previous`` (written into ``previous``
            # directly, flip's pass on two threads took a tenth longer).
            if num_actions == FIVE_ACTIONS:
                _boltzmann_five(rows, beta, weights, value)
            else:
                _boltzmann(rows, beta, num_actions, weights, total, value)
            for s in range(num_states):
                previous[s] = value[s]
            if keep_trace:
                values_t = values[t, k]
                jacobians_t = jacobians[t, k]
                for s in range(num_states):
                    values_t[s] = value[s]
                for a in range(num_actions):
                    for s in range(num_states):
                        i = a * num_states + s
                        jacobians_t[a, s] = weights[i] * multiply_add(beta, rows[i] - value[s], one)


@njit(inline="always", fastmath=False, error_model="numpy")
def _boltzmann(
    rows: np.ndarray,
    beta: float,
    num_actions: int,
    weights: np.ndarray,
    total: np.ndarray,
    value: np.ndarray,
) -> None:
    """A backup's Boltzmann policy (``weights``, rows as Q's) and value V_t from its rows Q_t
    (``total``: scratch of a weight per state)."""
    num_states = value.shape[0]
    for s in range(num_states):
        value[s] = 0.0
        # The state's best Q (the first of equal ones, its actions in order); shifted by it,
        # every exponent is <= 0 and the best weighs 1. A select, not a branch: the loop runs
        # as SIMD code (with an if, it stayed scalar and mispredicted).
        shift = rows[s]
        for a in range(1, num_actions):
            candidate = rows[a * num_states + s]
            shift = candidate if candidate > shift else shift
        sum_ = zero_as(beta)
        for a in range(num_actions):
            i = a * num_states + s
            weight = exp_nonpositive_one(beta * (rows[i] - shift))
            weights[i] = weight
            sum_ += weight
        total[s] = sum_
    for a in range(num_actions):
        _normalise(
            weights[a * num_states : (a + 1) * num_states],
            rows[a * num_states : (a + 1) * num_states],
            total,
            value,
        )


@njit(inline="always", fastmath=False, error_model="numpy")
def _boltzmann_five(rows: np.ndarray, beta: float, weights: np.ndarray, value: np.ndarray) -> None:
    """``_boltzmann`` of five actions: the same arithmetic in the same order, in one loop
    over states (its loops over actions unrolled, each state's five exps interleaved, see
    ``exp_nonpositive_five``)."""
    num_states = value.shape[0]
    for s in range(num_states):
        q0 = rows[s]
        q1 = rows[num_states + s]
        q2 = rows[2 * num_states + s]
        q3 = rows[3 * num_states + s]
        q4 = rows[4 * num_states + s]
        shift = q0
        shift = q1 if q1 > shift else shift
        shift = q2 if q2 > shift else shift
        shift = q3 if q3 > shift else shift
        shift = q4 if q4 > shift else shift
        w0, w1, w2, w3, w4 = exp_nonpositive_five(
            beta * (q0 - shift),
            beta * (q1 - shift),
            beta * (q2 - shift),
            beta * (q3 - shift),
            beta * (q4 - shift),
        )
        total = w0 + w1 + w2 + w3 + w4  # the loop's sum from 0: 0 + w0 is w0
        w0 = w0 / total
        w1 = w1 / total
        w2 = w2 / total
        w3 = w3 / total
        w4 = w4 / total
        weights[s] = w0
        weights[num_states + s] = w1
        weights[2 * num_states + s] = w2
        weights[3 * num_states + s] = w3
        weights[4 * num_states + s] = w4
        v = zero_as(q0)
        v = multiply_add(w0, q0, v)
        v = multiply_add(w1, q1, v)
        v = multiply_add(w2, q2, v)
        v = multiply_add(w3, q3, v)
        value[s] = multiply_add(w4, q4, v)


@njit(inline="never", fastmath=False, error_model="numpy")
def _normalise(weights: np.ndarray, rows: np.ndarray, total: np.ndarray, value: np.ndarray) -> None:
    """One action's weights divided by their state's total, and their terms of the value
    added (a separate function: inlined, its loop stayed scalar)."""
    for s in range(weights.shape[0]):
        weight = weights[s] / total[s]
        weights[s] = weight
        value[s] += weight * rows[s]


@njit(cache=True)
def incoming(
    next_flat: np.ndarray, probs_flat: np.ndarray, width: int, num_states: int, num_actions: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The non-zero entries by next state (the transpose of the table) for reverse passes, by
    level: every next state's first entry (in table order), then every second one, and so on,
    so that a reverse pass adding them level by level into zeros sums each next state's terms
    in table order, as a loop over its entries would, without that variable-length inner loop.

    The levels that most states have (navigation: all nine; flip: five of twelve) are dense,
    ``dense_sources[l, s]`` and ``dense_probabilities[l, s]`` for every state s, a state without
    an l-th entry padded with probability 0 (adding 0 * g leaves a sum that starts from +0 as
    it is, the sign of a zero included), so that a level is one loop over states the compiler
    turns into SIMD code. The others are flat triples: row ``sources[e]`` reaches next state
    ``targets[e]`` with ``probabilities[e]``, states in table order within a level. Sources are
    the passes' rows ``a * S + s``."""
    counts = np.zeros(num_states, dtype=np.int64)
    for j in range(next_flat.shape[0]):
        if probs_flat[j] != 0.0:
            counts[next_flat[j]] += 1
    most = 0
    for s in range(num_states):
        most = max(most, counts[s])
    # level_size[l]: the states with an (l + 1)-th entry (decreasing in l).
    level_size = np.zeros(most, dtype=np.int64)
    for s in range(num_states):
        for level in range(counts[s]):
            level_size[level] += 1
    num_dense = 0
    while num_dense < most and 2 * level_size[num_dense] >= num_states:
        num_dense += 1
    dense_sources = np.zeros((num_dense, num_states), dtype=np.int64)
    dense_probabilities = np.zeros((num_dense, num_states))
    level_start = np.zeros(most + 1, dtype=np.int64)
    for level in range(num_dense, most):
        level_start[level + 1] = level_start[level] + level_size[level]
    total = level_start[most]
    targets = np.empty(total, dtype=np.int64)
    sources = np.empty(total, dtype=np.int64)
    probabilities = np.empty(total)
    seen = np.zeros(num_states, dtype=np.int64)
    # Within a sparse level, states in table order of their entries; a state's l-th entry goes
    # to level l, so each state's entries keep table order across levels.
    fill = level_start[:-1].copy()
    for j in range(next_flat.shape[0]):
        if probs_flat[j] != 0.0:
            s = next_flat[j]
            level = seen[s]
            source = pass_row(j // width, num_states, num_actions)
            if level < num_dense:
                dense_sources[level, s] = source
                dense_probabilities[level, s] = probs_flat[j]
            else:
                e = fill[level]
                targets[e] = s
                sources[e] = source
                probabilities[e] = probs_flat[j]
                fill[level] += 1
            seen[s] += 1
    return dense_sources, dense_probabilities, targets, sources, probabilities


@njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def soft_backward_tasks(
    rows: ForwardLayout,
    incoming: ReverseLayout,
    scatter: bool,
    trace: Trace,
    d_q: np.ndarray,
    horizon: int,
    d_reward: np.ndarray,
    gradient: TableGradient,
    first: int,
    last: int,
) -> None:
    """Tasks ``first .. last - 1`` of a reverse pass from dL/dQ (K, S, A): dL/dreward added
    into ``d_reward`` (K, S), and dL/d(table entries) at the flat entry indices
    ``gradient.entries`` into ``gradient.d_probs`` (none: no transition gradient). Each next
    state's dL/dV is summed from the table by next state (``incoming``, float64 passes) or,
    with ``scatter``, through the forward layout (``rows``, float32 passes). The trace comes
    from ``soft_forward_tasks`` (its Q is not read).

    The transition gradient sums over tasks and backups. Tasks before ``kept_from`` add their
    terms into ``d_probs`` at once (one thread, or the first chunk of a split); from
    ``kept_from`` on, term (k, t, e) is kept in ``terms[k - kept_from, horizon - t, e]`` and
    ``add_terms`` adds them after the earlier tasks' sums, in the one-thread order, so that a
    split of the tasks over threads gives the same bits.

    With ``task_sums`` not empty (a whole table's gradient), no task adds at once: each task's
    terms are summed from 0 into ``task_sums[k, 0]``, for ``add_terms`` to add task by task
    (the order for every split, one thread's included); every chunk then works on its own."""
    # This chunk's rows of ``terms``: none for tasks before kept_from (they add at once).
    kept_from = gradient.kept_from
    start = max(0, first - kept_from)
    stop = max(0, last - kept_from) if first >= kept_from else 0
    chunk_terms = gradient.terms[start:stop]
    chunk_sums = gradient.task_sums[first:last]  # none without task sums
    num_actions = d_q.shape[2]
    if num_actions == FIVE_ACTIONS:
        _soft_backward(
            rows, incoming, scatter, trace, d_q, horizon, d_reward, gradient, chunk_terms,
            chunk_sums, first, last, FIVE_ACTIONS,
        )  # fmt: skip
    else:
        _soft_backward(
            rows, incoming, scatter, trace, d_q, horizon, d_reward, gradient, chunk_terms,
            chunk_sums, first, last, num_actions,
        )  # fmt: skip


@njit(inline="always", fastmath=False, error_model="numpy")
def _soft_backward(
    rows: ForwardLayout,
    incoming: ReverseLayout,
    scatter: bool,
    trace: Trace,
    d_q: np.ndarray,
    horizon: int,
    d_reward: np.ndarray,
    gradient: TableGradient,
    terms: np.ndarray,
    task_sums: np.ndarray,
    first: int,
    last: int,
    num_actions: int,
) -> None:
    """``soft_backward_tasks`` with this chunk's rows of the kept terms and task sums (those
    of ``gradient`` are not read). One loop over tasks and backups whose three ways of summing
    the transition gradient (terms kept, entries in runs, entries alone) share the scratch
    arrays set up before it."""
    _, values, jacobians = trace
    next_flat, width, gradient_entries, entry_runs, entry_slots, d_probs, _, _, _ = gradient
    num_states = d_q.shape[1]
    n = num_states * num_actions
    num_entries = gradient_entries.shape[0]
    keep_terms = terms.shape[0] > 0
    by_task = task_sums.shape[0] > 0
    # The pass's row (a * S + s) and the next state of each entry, and the sums of its terms
    # kept side by side (from d_probs, and written back at the end): the terms of a backup then
    # go into consecutive places, a loop the compiler vectorises, each entry's sum in the same
    # order as in place (doorway: 880 scattered additions per backup before).
    entry_rows, entry_next, entry_sums = _entry_places(
        gradient_entries,
        next_flat,
        width,
        num_states,
        num_actions,
        d_probs,
        not (keep_terms or by_task),
    )
    dtype = d_q.dtype  # float64, or float32 passes
    # Entries in runs of states (``entry_runs``: one action and offset, states lo .. hi - 1,
    # their sums from ``at`` on, see ``planning._entry_runs``) are summed side by side in
    # ``run_sums``, a SIMD loop over the run's states per backup instead of two gathers per
    # entry; each entry's sum takes the same terms in the same order, so the same bits. The
    # others, and every entry when terms are kept, as before.
    in_runs = entry_runs.shape[0] > 0 and not (keep_terms or by_task)
    run_size = 0
    if in_runs:
        for r in range(entry_runs.shape[0]):
            run_size += entry_runs[r, 3] - entry_runs[r, 2]
    run_sums = np.zeros(run_size, dtype)
    alone = np.empty(num_entries if in_runs else 0, dtype=np.int64)
    num_alone = 0
    if in_runs:
        for e in range(num_entries):
            if entry_slots[e] >= 0:
                run_sums[entry_slots[e]] = entry_sums[e]
            else:
                alone[num_alone] = e
                num_alone += 1
    g = np.empty(n, dtype)  # dL/dQ_t, row a * S + s
    shifted_flat = rows.shifted_probability.reshape(-1)
    g_v = np.empty(num_states, dtype)
    acc = np.empty(num_states, dtype)
    for k in range(first, last):
        if by_task:
            entry_sums[:] = 0.0
        for s in range(num_states):
            for a in range(num_actions):
                g[a * num_states + s] = d_q[k, s, a]
        d_reward_k = d_reward[k]
        for t in range(horizon, 0, -1):
            for s in range(num_states):
                acc[s] = 0.0
            for a in range(num_actions):
                for s in range(num_states):
                    acc[s] += g[a * num_states + s]
            for s in range(num_states):
                d_reward_k[s] += acc[s]
            if t == 1:
                break
            if num_entries > 0:
                v = values[t - 2, k]
                # Unsigned indices, as in the forward pass's gathers.
                if keep_terms:
                    kept = terms[k - first, horizon - t]
                    for e in range(num_entries):
                        kept[e] = g[np.uint64(entry_rows[e])] * v[np.uint64(entry_next[e])]
                elif in_runs:
                    for r in range(entry_runs.shape[0]):
                        a, d, lo, hi = (
                            entry_runs[r, 0],
                            entry_runs[r, 1],
                            entry_runs[r, 2],
                            entry_runs[r, 3],
                        )
                        row = np.uint64(a * num_states + lo)
                        source = np.uint64(lo + d)
                        at = np.uint64(entry_runs[r, 4])
                        for j in range(np.uint64(hi - lo)):
                            run_sums[at + j] += g[row + j] * v[source + j]
                    for i in range(num_alone):
                        e = alone[i]
                        entry_sums[e] += g[np.uint64(entry_rows[e])] * v[np.uint64(entry_next[e])]
                else:
                    for e in range(num_entries):
                        entry_sums[e] += g[np.uint64(entry_rows[e])] * v[np.uint64(entry_next[e])]
            if scatter:
                _scatter_levels(g_v, g, rows, shifted_flat)
            else:
                _dense_levels(g_v, incoming.dense_sources, incoming.dense_probabilities, g)
                _, _, targets, sources, probabilities = incoming
                for e in range(targets.shape[0]):
                    target = np.uint64(targets[e])
                    g_v[target] = g_v[target] + probabilities[e] * g[np.uint64(sources[e])]
            jacobians_t = jacobians[t - 2, k]
            for a in range(num_actions):
                for s in range(num_states):
                    g[a * num_states + s] = g_v[s] * jacobians_t[a, s]
        if by_task:
            task_sums[k - first, 0, :] = entry_sums
    if in_runs:
        for e in range(num_entries):
            if entry_slots[e] >= 0:
                entry_sums[e] = run_sums[entry_slots[e]]
    if not (keep_terms or by_task):
        for e in range(num_entries):
            d_probs[gradient_entries[e]] = entry_sums[e]


@njit(inline="always")
def _entry_places(
    gradient_entries: np.ndarray,
    next_flat: np.ndarray,
    width: int,
    num_states: int,
    num_actions: int,
    d_probs: np.ndarray,
    from_d_probs: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each gradient entry's pass row and next state, and its sum's start (its ``d_probs``,
    or 0), side by side."""
    count = gradient_entries.shape[0]
    rows = np.empty(count, dtype=np.int64)
    nexts = np.empty(count, dtype=np.int64)
    sums = np.empty(count, d_probs.dtype)
    for e in range(count):
        j = gradient_entries[e]
        rows[e] = pass_row(j // width, num_states, num_actions)
        nexts[e] = next_flat[j]
        sums[e] = d_probs[j] if from_d_probs else 0.0
    return rows, nexts, sums


@njit(inline="never", fastmath=False, error_model="numpy")
def _dense_levels(
    g_v: np.ndarray, sources: np.ndarray, probabilities: np.ndarray, g: np.ndarray
) -> None:
    """The transposed table's dense levels' terms summed into ``g_v`` from zero, level by
    level: each state's sum in level order, four levels to a loop over states (one loop per
    level loaded and stored the sums once per level)."""
    num_states = g_v.shape[0]
    for s in range(num_states):
        g_v[s] = 0.0
    num_levels = sources.shape[0]
    level = 0
    # Unsigned gathers (each source lies in ``g``), as in the passes' other gathers.
    while level + 4 <= num_levels:
        for s in range(num_states):
            g_v[s] = (
                ((g_v[s] + probabilities[level, s] * g[np.uint64(sources[level, s])])
                 + probabilities[level + 1, s] * g[np.uint64(sources[level + 1, s])])
                + probabilities[level + 2, s] * g[np.uint64(sources[level + 2, s])]
            ) + probabilities[level + 3, s] * g[np.uint64(sources[level + 3, s])]  # fmt: skip
        level += 4
    while level < num_levels:
        for s in range(num_states):
            g_v[s] = g_v[s] + probabilities[level, s] * g[np.uint64(sources[level, s])]
        level += 1


@njit(inline="always", fastmath=False, error_model="numpy")
def _scatter_levels(
    g_v: np.ndarray, g: np.ndarray, rows: ForwardLayout, shifted_flat: np.ndarray
) -> None:
    """dL/dV_t-1 into ``g_v`` from dL/dQ_t (``g``) through the forward pass's layout (``rows``,
    its shifted rows' probabilities flat in ``shifted_flat``): each shifted row's terms added
    into the next states at its offset as one SIMD loop over states, then the flat triples,
    level by level. Each next state's terms are summed in the forward layout's order, not the
    table's (the float32 passes' reverse pass)."""
    shifts, _, shift_start, flat_rows, flat_next, flat_probability, flat_start = rows
    num_states = g_v.shape[0]
    for s in range(num_states):
        g_v[s] = 0.0
    for level in range(shift_start.shape[0] - 1):
        for k in range(shift_start[level], shift_start[level + 1]):
            a, d, lo, hi = shifts[k, 0], shifts[k, 1], shifts[k, 2], shifts[k, 3]
            # Unsigned indices, as in the forward pass (each lies in its array).
            to = np.uint64(lo + d)
            at = np.uint64(k * num_states + lo)
            row = np.uint64(a * num_states + lo)
            for j in range(np.uint64(hi - lo)):
                g_v[to + j] = multiply_add(shifted_flat[at + j], g[row + j], g_v[to + j])
        for e in range(np.uint64(flat_start[level]), np.uint64(flat_start[level + 1])):
            target = np.uint64(flat_next[e])
            g_v[target] = multiply_add(flat_probability[e], g[np.uint64(flat_rows[e])], g_v[target])


@njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def add_terms(terms: np.ndarray, gradient_entries: np.ndarray, d_probs: np.ndarray) -> None:
    """The transition gradient's terms kept by ``soft_backward_tasks``, added into
    ``d_probs`` task by task and backup by backup: the one-thread pass's order of additions.
    The entries are distinct; their sums are kept side by side while the terms go in (a loop
    the compiler vectorises; in place, each addition was a gather and a scatter)."""
    num_entries = gradient_entries.shape[0]
    sums = np.empty(num_entries, d_probs.dtype)
    for e in range(num_entries):
        sums[e] = d_probs[gradient_entries[e]]
    for k in range(terms.shape[0]):
        for step in range(terms.shape[1]):
            kept = terms[k, step]
            for e in range(num_entries):
                sums[e] += kept[e]
    for e in range(num_entries):
        d_probs[gradient_entries[e]] = sums[e]


@njit(cache=True)
def hard_backups(
    next_flat: np.ndarray,
    probs_flat: np.ndarray,
    width: int,
    rewards: np.ndarray,
    horizon: int,
    num_actions: int,
):
    num_tasks, num_states = rewards.shape
    q = np.empty((num_tasks, num_states, num_actions))
    previous = np.zeros(num_states)
    current = np.zeros(num_states)
    for k in range(num_tasks):
        for s in range(num_states):
            previous[s] = 0.0
        for t in range(horizon):
            for s in range(num_states):
                best = -np.inf
                for a in range(num_actions):
                    acc = rewards[k, s]
                    if t > 0:
                        base = (s * num_actions + a) * width
                        for m in range(width):
                            acc += probs_flat[base + m] * previous[next_flat[base + m]]
                    q[k, s, a] = acc
                    if acc > best:
                        best = acc
                current[s] = best
            for s in range(num_states):
                previous[s] = current[s]
    return q


# -- the passes' chunks on numba's OpenMP threads ------------------------------------------------
# A pass's chunks of tasks (or of a whole table's entries), each the one-thread kernel above on
# its own range, run by the threads of a parallel loop. Handing a chunk to a Python thread took
# 55 us and a sleeping thread's wake-up (this machine, a VM), more than a chunk's work in
# navigation; OpenMP's threads wait spinning between passes (2.6 us per launch).


@njit(cache=True, parallel=True, nogil=True)
def probe_parallel(x: np.ndarray) -> None:
    """A parallel loop of nothing: starts the threading layer (planning.compiled_threads)."""
    for i in prange(x.shape[0]):
        x[i] += 1.0


@njit(cache=True, parallel=True, nogil=True)
def soft_forward_chunks(rows, rewards, beta, horizon, keep_trace, trace, firsts, lasts):  # type: ignore[no-untyped-def]
    """``soft_forward_tasks`` on the task ranges ``firsts[c] .. lasts[c] - 1``, in parallel."""
    for c in prange(firsts.shape[0]):
        soft_forward_tasks(rows, rewards, beta, horizon, keep_trace, trace, firsts[c], lasts[c])


@njit(cache=True, parallel=True, nogil=True)
def soft_backward_chunks(  # type: ignore[no-untyped-def]
    rows, incoming, scatter, trace, d_q, horizon, d_reward, gradient, firsts, lasts
):
    """``soft_backward_tasks`` on the task ranges ``firsts[c] .. lasts[c] - 1``, in parallel."""
    for c in prange(firsts.shape[0]):
        soft_backward_tasks(
            rows, incoming, scatter, trace, d_q, horizon, d_reward, gradient, firsts[c], lasts[c]
        )


# -- a learner's cost steps, compiled whole --------------------------------------------------------


@njit(inline="always", fastmath=False, error_model="numpy")
def norm_in_fours(x: np.ndarray, first: int, last: int) -> float:
    """The Euclidean norm of ``x[first:last]``, its squares summed in four running sums (one
    chain of dependent additions was the slowest part of a momentum step), then paired."""
    sums = np.zeros(4, x.dtype)
    stop = last - (last - first) % 4
    for i in range(first, stop, 4):
        for j in range(4):
            sums[j] += x[i + j] * x[i + j]
    for i in range(stop, last):
        sums[0] += x[i] * x[i]
    return np.sqrt((sums[0] + sums[1]) + (sums[2] + sums[3]))


@njit(inline="always", fastmath=False, error_model="numpy")
def clipped_momentum_step(
    parameters: np.ndarray,
    velocity: np.ndarray,
    gradient: np.ndarray,
    learning_rate: float,
    momentum: float,
    max_step: float,
    clip_step: bool,
    bound: float,
) -> bool:
    """``MomentumAscent.step`` of one row of parameters (and its velocity) in place, the
    parameters then clipped to +-``bound``; False where the velocity's norm is not finite
    (a gradient that is not)."""
    size = parameters.shape[0]
    for i in range(size):
        velocity[i] = momentum * velocity[i] + learning_rate * gradient[i]
    norm = norm_in_fours(velocity, 0, size)
    if not np.isfinite(norm):
        return False
    scale = max_step / max(norm, 1e-300) if norm > max_step else 1.0
    for i in range(size):
        change = velocity[i] * scale
        if not clip_step:
            velocity[i] = change
        parameters[i] = min(max(parameters[i] + change, -bound), bound)
    return True


@njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def cost_steps_tasks(
    rows: ForwardLayout,
    incoming: ReverseLayout,
    scatter: bool,
    no_gradient: TableGradient,
    pass_beta: float,
    horizon: int,
    cells: CostCells,
    records: TaskRecords,
    models: TeacherModels,
    steps: int,
    prior_variance: float,
    step_settings: StepSettings,
    trace: Trace,
    workspace: CostWorkspace,
    state: CostState,
    first: int,
    last: int,
) -> None:
    """``steps`` cost steps of the tasks ``first .. last - 1`` (the environment's), each task's
    costs (``state.costs[task]``, per cell) with an optimiser of its own (its velocity): what
    ``CellCosts.step`` (cost_fit) does, element by element in the same order, but for the
    norm that clips a step (``norm_in_fours``) and a feedback step's sigmoid (the C library's
    tanh). A task with data (``cells.data_row[task]``, its row in the passes' arrays) plans on
    rewards from its costs over ``plan_states`` (a forward pass), takes its demonstrations'
    and agent steps' log-likelihood (``records``, in the data's order) and dL/dQ, and the
    reverse pass's dL/drewards (``no_gradient``: of the rewards alone) summed to its cells;
    every task adds its costs' prior. Tasks are independent: any split of them over threads
    computes the same bits. Called once an update, it is split over Python threads (it holds
    no GIL), not by a parallel version of its own, which only took as long again to compile
    (about 20 s of a core). At the last step's start each task's costs go to ``state.before``
    and its records' log-likelihoods to ``demo_values`` and ``step_values`` (at their places in
    the data), for the objective; an error stops the task with its code in ``codes[task]`` (the
    likelihood's, ``GRADIENT_NOT_FINITE``, ``LIKELIHOOD_NOT_FINITE``). One loop over a task's
    steps, as ``cost_step`` is one step: each step's stages (rewards, forward pass, likelihood,
    reverse pass, the gradient by cell, the prior, the momentum step) read the one before's
    arrays."""
    data_row, plan_states, state_cells, num_features, cost_mask = cells
    (
        demo_rows, demo_start, demo_states, demo_actions, step_rows, step_start, step_states,
        step_actions, step_feedback,
    ) = records  # fmt: skip
    beta, normalized, variance_floor, epsilon, alpha, mu_plus, mu_minus = models
    rewards, d_reward, d_q = workspace
    costs, velocity, before, demo_values, step_values, codes = state
    q = trace.q
    num_cells = costs.shape[1]
    num_plan = plan_states.shape[0]
    num_actions = q.shape[2]
    any_steps = step_rows.shape[0] > 0
    gradient = np.empty(num_cells)
    d_full = np.zeros(state_cells.shape[0])
    q_row = np.empty((1, num_plan, num_actions))
    no_sigmoids = np.empty(0)
    for task in range(first, last):
        row = data_row[task]
        parameters = costs[task]
        demos = demo_start[row + 1] - demo_start[row] if row >= 0 else 0
        agent_steps = step_start[row + 1] - step_start[row] if row >= 0 else 0
        local_demos = np.zeros(demos, dtype=np.int64)  # the task's rows of q_row: row 0
        local_steps = np.zeros(agent_steps, dtype=np.int64)
        for step in range(steps):
            last_step = step == steps - 1
            if last_step:
                before[task, :] = parameters
            if row >= 0:
                for j in range(num_plan):
                    rewards[row, j] = parameters[state_cells[plan_states[j]]]
                soft_forward_tasks(
                    rows, rewards, pass_beta, horizon, np.bool_(True), trace, row, row + 1,  # type: ignore[arg-type]  # a NumPy scalar: no literal
                )  # fmt: skip
                for s in range(num_plan):
                    for a in range(num_actions):
                        q_row[0, s, a] = q[row, s, a]
                d0, d1 = demo_start[row], demo_start[row + 1]
                s0, s1 = step_start[row], step_start[row + 1]
                sigmoids = no_sigmoids
                if agent_steps:
                    advantages, code = step_advantages(
                        q_row, local_steps, step_states[s0:s1], step_actions[s0:s1],
                        step_feedback[s0:s1],
                    )  # fmt: skip
                    if code:
                        codes[task] = code
                        break
                    sigmoids = 0.5 * (1.0 + np.tanh(0.5 * (alpha * advantages)))
                demo_row_values, d_q_demos, step_row_values, d_q_steps, code = (
                    data_log_likelihood_kernel(
                        q_row, local_demos, demo_states[d0:d1], demo_actions[d0:d1],
                        beta, normalized, variance_floor,
                        local_steps, step_states[s0:s1], step_actions[s0:s1],
                        step_feedback[s0:s1], sigmoids, epsilon, alpha, mu_plus, mu_minus,
                    )
                )  # fmt: skip
                if code:
                    codes[task] = code
                    break
                finite = True
                for n in range(demos):
                    finite = finite and np.isfinite(demo_row_values[n])
                for n in range(agent_steps):
                    finite = finite and np.isfinite(step_row_values[n])
                if not finite:
                    codes[task] = LIKELIHOOD_NOT_FINITE
                    break
                if last_step:
                    for n in range(demos):
                        demo_values[demo_rows[d0 + n]] = demo_row_values[n]
                    for n in range(agent_steps):
                        step_values[step_rows[s0 + n]] = step_row_values[n]
                # dL/dQ in the passes' precision (the steps' terms added where any task has
                # agent steps, as data_log_likelihood adds them).
                for s in range(num_plan):
                    for a in range(num_actions):
                        g = d_q_demos[0, s, a]
                        if any_steps:
                            g = g + d_q_steps[0, s, a]
                        d_q[row, s, a] = g
                for s in range(num_plan):
                    d_reward[row, s] = 0.0
                soft_backward_tasks(
                    rows, incoming, scatter, trace, d_q, horizon, d_reward, no_gradient, row,
                    row + 1,
                )  # fmt: skip
                # dL/dcost of a cell: its states' dL/dreward (0 out of the data's reach) in
                # feature order, as NumPy's sum over the features adds them.
                for j in range(num_plan):
                    d_full[plan_states[j]] = d_reward[row, j]
                for c in range(num_cells):
                    total = d_full[c * num_features]
                    for f in range(1, num_features):
                        total = total + d_full[c * num_features + f]
                    gradient[c] = total * cost_mask[c]
            else:
                gradient[:] = 0.0
            for c in range(num_cells):
                gradient[c] = gradient[c] + -(parameters[c] - 0.0) / prior_variance
            learning_rate, momentum, max_step, clip_step, bound = step_settings
            if not clipped_momentum_step(
                parameters, velocity[task], gradient, learning_rate, momentum, max_step,
                clip_step, bound,
            ):  # fmt: skip
                codes[task] = GRADIENT_NOT_FINITE
                break


# -- a learner's steps on theta and its dynamics steps, compiled whole -----------------------------

# The model spaces whose steps on theta compile (``theta_steps``), by their primitives:
# sigmoid(theta) per parameter (navigation), a softmax over each row of ``choices`` (gravity,
# farming).
SIGMOID_PRIMITIVES = 0
SOFTMAX_ROWS_PRIMITIVES = 1


@njit(inline="always", fastmath=False, error_model="numpy")
def _primitives(family: int, choices: int, theta: np.ndarray, p: np.ndarray) -> None:
    """The model space's primitive probabilities at ``theta`` into ``p`` (its ``primitives``)."""
    if family == SIGMOID_PRIMITIVES:
        for i in range(theta.shape[0]):
            p[i] = 0.5 * (1.0 + np.tanh(0.5 * theta[i]))
        return
    for g in range(0, theta.shape[0], choices):
        top = theta[g]
        for j in range(1, choices):
            top = max(top, theta[g + j])
        total = 0.0
        for j in range(choices):
            p[g + j] = np.exp(theta[g + j] - top)
            total += p[g + j]
        for j in range(choices):
            p[g + j] = p[g + j] / total


@njit(inline="always", fastmath=False, error_model="numpy")
def _add_primitives_pullback(
    family: int, choices: int, p: np.ndarray, d_p: np.ndarray, gradient: np.ndarray
) -> None:
    """dL/dtheta from dL/dp (``primitives_pullback``) added into ``gradient``."""
    if family == SIGMOID_PRIMITIVES:
        for i in range(p.shape[0]):
            gradient[i] = gradient[i] + d_p[i] * p[i] * (1.0 - p[i])
        return
    for g in range(0, p.shape[0], choices):
        dot = 0.0
        for j in range(choices):
            dot += d_p[g + j] * p[g + j]
        for j in range(choices):
            gradient[g + j] = gradient[g + j] + p[g + j] * (d_p[g + j] - dot)


@njit(inline="always", fastmath=False, error_model="numpy")
def _outcome_factor(outcome: int, t: float, pk: float) -> float:
    """``domains.base._outcome_factors`` of one entry."""
    over_p = t / pk if pk > 0.0 else 1.0
    over_q = t / (1.0 - pk) if pk < 1.0 else 1.0
    return 2.0 * over_p if outcome > 0 else -over_q - over_p


@njit(inline="always", fastmath=False, error_model="numpy")
def _theta_gradient(
    theta: np.ndarray,
    p: np.ndarray,
    model: tuple,  # type: ignore[type-arg]
    d_teacher: np.ndarray,
    gradient: np.ndarray,
) -> tuple[float, int, int]:
    """The observed transitions' log-likelihood plus the dynamics prior at ``theta`` (whose
    primitives are ``p``), and into ``gradient`` its gradient plus, if ``d_teacher`` is not
    empty, the teacher data's gradient on the moved entries of the table it was planned on
    pulled back to theta; an error code and the observed row it is about. ``model``: what
    ``theta_steps`` describes."""
    (
        family, choices, observed, num_observed, authors_observed, moved_coef, moved_index,
        taught, authors_teacher, prior_mean, prior_variance, _,
    ) = model  # fmt: skip
    const, coef, index, rows, moved_places, moved_rows, first_outcomes, first_index = observed
    taught_const, taught_coef, taught_index, taught_outcomes = taught
    num_parameters = theta.shape[0]
    d_p = np.zeros(num_parameters)
    gradient[:] = 0.0
    value = 0.0
    if num_observed > 0:
        row_probability = np.zeros(num_observed)
        for e in range(rows.shape[0]):
            row_probability[rows[e]] += const[e] + coef[e] * p[index[e]]
        for n in range(num_observed):
            if row_probability[n] <= 0.0:
                # Rounded to 0 at this theta (a saturated logit): the least probability where
                # the model space can give the row some, else impossible.
                possible = False
                for e in range(rows.shape[0]):
                    if rows[e] == n and (coef[e] != 0.0 or const[e] > 0.0):
                        possible = True
                if not possible:
                    return value, IMPOSSIBLE_TRANSITION, n
                value += np.log(LEAST_PROBABILITY)
            else:
                value += np.log(row_probability[n])
        if authors_observed:
            for n in range(first_index.shape[0]):
                k = first_index[n]
                d_p[k] += _outcome_factor(first_outcomes[n], 1.0, p[k])
        else:
            d_moved = np.zeros(moved_coef.shape[0])
            for n in range(moved_places.shape[0]):
                row = moved_rows[n]
                if row_probability[row] > 0.0:
                    d_moved[moved_places[n]] += 1.0 / row_probability[row]
            for e in range(moved_coef.shape[0]):
                d_p[moved_index[e]] += moved_coef[e] * d_moved[e]
        _add_primitives_pullback(family, choices, p, d_p, gradient)
    if prior_variance > 0.0:
        squares = 0.0
        for i in range(num_parameters):
            deviation = theta[i] - prior_mean
            squares += deviation * deviation
            gradient[i] = gradient[i] + -deviation / prior_variance
        value += -0.5 * squares / prior_variance
    if d_teacher.shape[0] > 0:
        teacher = np.zeros(num_parameters)
        d_p[:] = 0.0
        for e in range(d_teacher.shape[0]):
            k = taught_index[e]
            if authors_teacher:
                t = taught_const[e] + taught_coef[e] * p[k]
                d_p[k] += d_teacher[e] * _outcome_factor(taught_outcomes[e], t, p[k])
            else:
                d_p[k] += taught_coef[e] * d_teacher[e]
        _add_primitives_pullback(family, choices, p, d_p, teacher)
        for i in range(num_parameters):
            gradient[i] = gradient[i] + teacher[i]
    return value, 0, -1


@njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def theta_steps(
    theta: np.ndarray,
    velocity: np.ndarray,
    model: tuple,  # type: ignore[type-arg]
    steps: int,
    d_teacher: np.ndarray,
) -> tuple[float, int, int]:
    """``steps`` momentum steps on ``theta`` (and ``velocity``, in place) for the observed
    transitions' log-likelihood, the dynamics prior and, if ``d_teacher`` is not empty, the
    teacher data's gradient on the entries theta moves of the table it was planned on (the same
    at every step: one step of BAM): ``ThetaFit.transition_objective`` (dynamics_fit), ``pullback`` and
    ``theta_step`` element by element in their order, but for sums NumPy takes pairwise (the
    log-likelihood's value), the norm that clips a step (``norm_in_fours``) and the C library's
    tanh and exp. ``model``: the primitives' family and a softmax row's length; the observed
    transitions as ``TransitionModel.observe`` matched them (each entry's const, coef, primitive
    and observed row; the entries theta moves, their places and rows; the authors' farming
    rule's first outcomes and primitives), their count and whether the authors' rule applies;
    the model's moved entries' coefficients and primitives; the teacher's table's moved
    entries (const, coef, primitive, outcome) and whether the authors' rule applies to them;
    the prior's mean and variance (0: no prior); and the optimiser: learning rate, momentum,
    largest step, whether the step (not the velocity) is clipped, and the bound on theta
    (inf: none).

    Returns the objective (likelihood plus prior) at the last step's start, an error code (0,
    ``IMPOSSIBLE_TRANSITION`` with the observed row, ``GRADIENT_NOT_FINITE``) and the row."""
    family, choices = model[0], model[1]
    learning_rate, momentum, max_step, clip_step, bound = model[11]
    p = np.empty(theta.shape[0])
    gradient = np.empty(theta.shape[0])
    value = 0.0
    for _ in range(steps):
        _primitives(family, choices, theta, p)
        value, code, row = _theta_gradient(theta, p, model, d_teacher, gradient)
        if code:
            return value, code, row
        if not clipped_momentum_step(
            theta, velocity, gradient, learning_rate, momentum, max_step, clip_step, bound
        ):
            return value, GRADIENT_NOT_FINITE, -1
    return value, 0, -1


@njit(inline="always", fastmath=False, error_model="numpy")
def _teacher_gradient(passes: TeacherPasses) -> tuple[np.ndarray, np.ndarray, int]:
    """``teacher_gradient``."""
    (
        rows, incoming, scatter, rewards, pass_beta, horizon, trace, likelihood, d_reward, gradient,
        copies, originals,
    ) = passes  # fmt: skip
    (
        demo_tasks, demo_states, demo_actions, beta, normalized, variance_floor, step_tasks,
        step_states, step_actions, step_feedback, epsilon, alpha, mu_plus, mu_minus,
    ) = likelihood  # fmt: skip
    q, d_probs = trace.q, gradient.d_probs
    num_tasks = q.shape[0]
    soft_forward_tasks(
        rows, rewards, pass_beta, horizon, np.bool_(True), trace,  # type: ignore[arg-type]  # a NumPy scalar: no literal
        np.int64(0), num_tasks,  # type: ignore[arg-type]  # a NumPy scalar: no literal
    )  # fmt: skip
    q_data = q.astype(np.float64)
    no_values = np.empty(0)
    if step_tasks.shape[0] > 0:
        advantages, code = step_advantages(
            q_data, step_tasks, step_states, step_actions, step_feedback
        )
        if code:
            return no_values, no_values, code
        sigmoids = 0.5 * (1.0 + np.tanh(0.5 * (alpha * advantages)))
    else:
        sigmoids = np.empty(0)
    demo_values, d_q, step_values, d_q_steps, code = data_log_likelihood_kernel(
        q_data, demo_tasks, demo_states, demo_actions, beta, normalized, variance_floor,
        step_tasks, step_states, step_actions, step_feedback, sigmoids, epsilon, alpha,
        mu_plus, mu_minus,
    )  # fmt: skip
    if code:
        return no_values, no_values, code
    for n in range(demo_values.shape[0]):
        if not np.isfinite(demo_values[n]):
            return demo_values, step_values, LIKELIHOOD_NOT_FINITE
    for n in range(step_values.shape[0]):
        if not np.isfinite(step_values[n]):
            return demo_values, step_values, LIKELIHOOD_NOT_FINITE
    # dL/dQ rounded to the passes' precision (the agent steps' terms added where there are
    # any, as data_log_likelihood adds them).
    g_q = np.empty_like(q)
    any_steps = step_tasks.shape[0] > 0
    for k in range(num_tasks):
        for s in range(q.shape[1]):
            for a in range(q.shape[2]):
                g = d_q[k, s, a]
                if any_steps:
                    g = g + d_q_steps[k, s, a]
                g_q[k, s, a] = g
    for k in range(num_tasks):
        for s in range(d_reward.shape[1]):
            d_reward[k, s] = 0.0
    for j in range(d_probs.shape[0]):
        d_probs[j] = 0.0
    soft_backward_tasks(
        rows, incoming, scatter, trace, g_q, horizon, d_reward, gradient, np.int64(0),  # type: ignore[arg-type]  # a NumPy scalar: no literal
        num_tasks,
    )  # fmt: skip
    # Entries of a row that lead to one next state have one gradient (``distinct_entries``).
    for j in range(copies.shape[0]):
        d_probs[copies[j]] = d_probs[originals[j]]
    return demo_values, step_values, 0


@njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def teacher_gradient(passes: TeacherPasses) -> tuple[np.ndarray, np.ndarray, int]:
    """The teacher data's log-likelihood under a table and the learner's rewards, and its
    gradient on the table's entries and on the rewards, every task in this thread: what
    ``planned_teacher_log_likelihood`` with the transition gradient does on one planner thread
    (a forward pass of every task, the data's likelihood and dL/dQ from
    ``data_log_likelihood_kernel``, the reverse pass), the same operations in the same order but for
    a feedback step's sigmoid (the C library's tanh). dL/drewards and dL/dT written into
    ``passes``, then the entries ``copies`` given the gradient of the ``originals`` they copy
    (``TransitionOperator.reverse_entries``). Returns the demonstrations' and agent steps'
    log-likelihoods (for the caller to sum as NumPy sums them) and an error code (the
    likelihood's, ``LIKELIHOOD_NOT_FINITE``), the gradients unwritten on an error."""
    return _teacher_gradient(passes)


@njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def dynamics_steps(
    theta: np.ndarray,
    velocity: np.ndarray,
    model: tuple,  # type: ignore[type-arg]
    steps: int,
    probs_flat: np.ndarray,
    taught_entries: np.ndarray,
    nonzero: np.ndarray,
    layout_sources: tuple,  # type: ignore[type-arg]
    passes: TeacherPasses,
) -> tuple[float, np.ndarray, np.ndarray, int, int, int]:
    """``steps`` of BAM's dynamics steps: at each, the teacher's table at theta
    (``probs_flat``, the model's flat table with its moved entries ``taught_entries`` set from
    theta's primitives, and gathered into the layouts of ``passes`` (``rows``, ``incoming``),
    whose probabilities are its own, by ``layout_sources``: the shifted rows' and flat triples' entries, the dense
    levels' and the scattered entries', -1 for a probability 0), ``teacher_gradient``'s passes
    and likelihood on it, and ``theta_steps``' step with its gradient. Where a step's table has a moved entry zero that ``nonzero`` says is not, or the
    reverse, the layouts no longer fit: the steps stop before it (``LAYOUT_CHANGED``) for the
    caller to take the rest. Returns the objective besides the teacher's (likelihood plus
    prior) at the last step's start, the teacher data's log-likelihoods there, an error code,
    the steps done and the observed row of an error. ``model`` as ``theta_steps`` takes it."""
    family, choices, taught = model[0], model[1], model[7]
    learning_rate, momentum, max_step, clip_step, bound = model[11]
    d_probs = passes.gradient.d_probs
    p = np.empty(theta.shape[0])
    theta_gradient = np.empty(theta.shape[0])
    d_teacher = np.empty(taught_entries.shape[0])
    value = 0.0
    demo_values = np.empty(0)
    step_values = np.empty(0)
    taught_const, taught_coef, taught_index, _ = taught
    for step in range(steps):
        _primitives(family, choices, theta, p)
        for e in range(taught_entries.shape[0]):
            probability = taught_const[e] + taught_coef[e] * p[taught_index[e]]
            if (probability != 0.0) != nonzero[e]:
                return value, demo_values, step_values, LAYOUT_CHANGED, step, -1
            probs_flat[taught_entries[e]] = probability
        _fill_layouts(probs_flat, layout_sources, passes)
        demo_values, step_values, code = _teacher_gradient(passes)
        if code:
            return value, demo_values, step_values, code, step, -1
        for e in range(taught_entries.shape[0]):
            d_teacher[e] = np.float64(d_probs[taught_entries[e]])
        value, code, row = _theta_gradient(theta, p, model, d_teacher, theta_gradient)
        if code:
            return value, demo_values, step_values, code, step, row
        if not clipped_momentum_step(
            theta, velocity, theta_gradient, learning_rate, momentum, max_step, clip_step, bound
        ):
            return value, demo_values, step_values, GRADIENT_NOT_FINITE, step, -1
    return value, demo_values, step_values, 0, steps, -1


@njit(inline="always", fastmath=False, error_model="numpy")
def _fill_layouts(probs_flat: np.ndarray, layout_sources: tuple, passes: TeacherPasses) -> None:  # type: ignore[type-arg]
    """The table's probabilities into the passes' layouts in their precision (rounded from
    float64, as ``planning._PassLayout`` gathers them; source -1: 0): ``layout_sources``, the
    places' entries in the table (``dynamics_steps``)."""
    shifted_source, flat_source, dense_source, target_source = layout_sources
    _, shifted_probability, _, _, _, flat_probability, _ = passes.rows
    for g in range(shifted_source.shape[0]):
        for s in range(shifted_source.shape[1]):
            j = shifted_source[g, s]
            shifted_probability[g, s] = probs_flat[j] if j >= 0 else 0.0
    for e in range(flat_source.shape[0]):
        flat_probability[e] = probs_flat[flat_source[e]]
    if not passes.scatter:
        _, dense_probabilities, _, _, probabilities = passes.incoming
        for level in range(dense_source.shape[0]):
            for s in range(dense_source.shape[1]):
                j = dense_source[level, s]
                dense_probabilities[level, s] = probs_flat[j] if j >= 0 else 0.0
        for e in range(target_source.shape[0]):
            probabilities[e] = probs_flat[target_source[e]]
