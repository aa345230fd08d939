"""The learner's parametric transition model T_theta, linear in a small vector of "primitive"
probabilities p(theta): a sigmoid per navigation cell (``SigmoidModel``), a softmax row per
gravity colour or farming machine (``SoftmaxRowsModel``):

    T_theta(s, a, next_states[s, a, m]) = const[s, a, m] + coef[s, a, m] * p(theta)[index[s, a, m]]

which gives the log-likelihood of observed transitions and the pull-back of any gradient on T
to theta with the same few lines for every domain. The model's layout is the sparse tables'
(``tables``).
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from server.domains.tables import SparseTransitions, check_finite, check_shape, state_numbers

# Restricted models a model keeps (``TransitionModel.restricted``): a learner's data reaches
# one set of states per update, mostly the same from one update to the next.
RESTRICTIONS_KEPT = 8


class TransitionModel:
    """The learner's parametric dynamics model T_theta (see the module docstring).

    Over 250 lines because the model's transitions and the exact pull-back of a gradient to
    theta must agree term by term, and are kept side by side. Subclasses define the primitive probabilities p(theta) and their vector-Jacobian product.
    """

    def __init__(
        self,
        next_states: np.ndarray,
        const: np.ndarray,
        coef: np.ndarray,
        index: np.ndarray,
        num_parameters: int,
        initial_value: float,
        parameter_names: Sequence[str],
        prior_sd: float | None = None,
        parameter_bound: float | None = None,
        outcomes: np.ndarray | None = None,
    ) -> None:
        self.next_states = np.ascontiguousarray(next_states, dtype=np.int64)
        # + 0.0: a -0 becomes +0, as const + coef * p gives where coef is 0.
        self.const = np.ascontiguousarray(const, dtype=np.float64) + 0.0
        self.coef = np.ascontiguousarray(coef, dtype=np.float64)
        self.index = np.ascontiguousarray(index, dtype=np.int64)
        self.num_parameters = int(num_parameters)
        self.initial_value = float(initial_value)
        self.parameter_names = tuple(parameter_names)
        self.num_states, self.num_actions, self.width = self.next_states.shape
        # The model space's own prior on theta (the paper authors'): Gaussian of this deviation
        # centred on ``initial_value``, or None for none.
        self.prior_sd = None if prior_sd is None else float(prior_sd)
        # Where the authors clip theta after every update (None: nowhere).
        self.parameter_bound = None if parameter_bound is None else float(parameter_bound)
        # The authors' farming update is not the gradient of the likelihood: it treats each
        # parametric entry as a success (+1: the machine worked, or an action that stays on a
        # field, which their model counts as one) or a failure (-1); None where their update
        # is the exact gradient (see ``pullback`` and ``transition_log_likelihood``).
        self.outcomes = None if outcomes is None else np.ascontiguousarray(outcomes, dtype=np.int64)
        self._parametric = self.coef != 0.0
        # The table's layout flattened for the planner (fixed for the model's lifetime).
        self.flat_next_states = self.next_states.reshape(-1)
        self.flat_parametric_entries = np.flatnonzero(self._parametric.reshape(-1))
        self._last_probabilities: tuple[bytes, np.ndarray] | None = None
        self._last_primitives: tuple[bytes, np.ndarray] | None = None
        self._last_finite = b""  # the bytes of the last theta ``check_parameters`` passed
        self._restrictions: dict[bytes, TransitionModel] = {}
        # Whose kept primitives this model uses: a restricted model shares its model's.
        self._primitives_owner: TransitionModel = self
        self._const_flat = self.const.reshape(-1)
        self._coef_flat = self.coef.reshape(-1)
        self._index_flat = self.index.reshape(-1)
        self._parametric_coef = self._coef_flat[self.flat_parametric_entries]
        self._parametric_index = self._index_flat[self.flat_parametric_entries]
        self.moved_entries = MovedEntries(
            self._const_flat[self.flat_parametric_entries],
            self._parametric_coef,
            self._parametric_index,
            (
                np.zeros(self.flat_parametric_entries.size, dtype=np.int64)
                if self.outcomes is None
                else self.outcomes.reshape(-1)[self.flat_parametric_entries]
            ),
        )
        # Each entry's place among the entries theta moves, -1 for the others.
        self._moved_place = np.full(self._const_flat.size, -1, dtype=np.int64)
        self._moved_place[self.flat_parametric_entries] = np.arange(
            self.flat_parametric_entries.size
        )
        # The entries some theta makes non-zero.
        self._possible = (self.const != 0.0) | self._parametric

    # -- the states a set of states can reach -------------------------------------------
    def reachable(self, states: np.ndarray) -> np.ndarray:
        """The states reachable from ``states`` (included) through entries that are non-zero
        for some theta, sorted: a set no theta's table leads out of."""
        reached = np.zeros(self.num_states, dtype=bool)
        frontier = np.unique(np.asarray(states, dtype=np.int64))
        reached[frontier] = True
        while frontier.size:
            successors = np.unique(self.next_states[frontier][self._possible[frontier]])
            frontier = successors[~reached[successors]]
            reached[frontier] = True
        return np.flatnonzero(reached)

    def restricted(self, states: np.ndarray) -> TransitionModel:
        """This model over ``states`` only (sorted, a set ``reachable`` returns), its states
        numbered in their order: the same parameters and, at every theta, the same entries of
        those states' rows, in the same order. Kept per set (a learner asks at every update)."""
        states = np.asarray(states, dtype=np.int64)
        key = states.tobytes()
        known = self._restrictions.get(key)
        if known is not None:
            return known
        next_states = state_numbers(states, self.num_states)[self.next_states[states]]
        possible = self._possible[states]
        if np.any(next_states[possible] < 0):
            raise ValueError("the states must include every state they can reach")
        next_states[~possible] = 0  # entries of probability 0 for every theta
        model = copy.copy(self)  # a subclass's own settings (groups, choices) come along
        TransitionModel.__init__(
            model,
            next_states,
            self.const[states],
            self.coef[states],
            self.index[states],
            self.num_parameters,
            self.initial_value,
            self.parameter_names,
            self.prior_sd,
            self.parameter_bound,
            None if self.outcomes is None else self.outcomes[states],
        )
        model._primitives_owner = self._primitives_owner
        kept = self._restrictions if len(self._restrictions) < RESTRICTIONS_KEPT else {}
        # A new dict in one assignment: a thread reading the old one meanwhile is not disturbed.
        self._restrictions = {**kept, key: model}
        return model

    @property
    def parametric_entries(self) -> np.ndarray:
        """(S, A, M) mask of the entries that depend on theta: ``pullback`` reads only these."""
        return self._parametric

    # -- primitives, defined by subclasses -------------------------------------------------
    @property
    def num_primitives(self) -> int:
        raise NotImplementedError

    def primitives(self, theta: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def primitives_pullback(self, theta: np.ndarray, d_primitives: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    # -- the model ------------------------------------------------------------------------
    def initial_parameters(self) -> np.ndarray:
        return np.full(self.num_parameters, self.initial_value)

    def check_parameters(self, theta: np.ndarray) -> np.ndarray:
        theta = check_shape("dynamics parameters", theta, (self.num_parameters,))
        theta = np.asarray(theta, dtype=np.float64)
        # A learner's step asks for one theta three times (its likelihood, its table, the
        # pull-back): the last theta found finite is known by its bytes.
        key = theta.tobytes()
        if key != self._primitives_owner._last_finite:
            check_finite("dynamics parameters", theta)
            self._primitives_owner._last_finite = key
        return theta

    def probabilities(self, theta: np.ndarray) -> np.ndarray:
        """The (S, A, M) table's probabilities at ``theta`` (a new array each call).

        The last theta's table is kept: a learner's step asks for it twice (the observed
        transitions' likelihood, then the planner's table), and flip's takes 25 us."""
        theta = self.check_parameters(theta)
        key = theta.tobytes()
        last = self._last_probabilities
        if last is None or last[0] != key:
            # const + coef * p[index], computed where coef is not 0 (flip: 216 of 8000
            # entries); elsewhere it is const (+0 for a -0, which __init__ made +0 already).
            table = self._const_flat.copy()
            moved = self.flat_parametric_entries
            table[moved] = self._entry_probabilities(self._primitives_at(theta), moved)
            last = (key, table.reshape(self.next_states.shape))
            self._last_probabilities = last  # one assignment: threads see a consistent pair
        return last[1].copy()

    def _entry_probabilities(self, p: np.ndarray, entries: np.ndarray) -> np.ndarray:
        """The table's flat ``entries`` at primitives ``p``: const + coef * p[index]."""
        return self._const_flat[entries] + self._coef_flat[entries] * p[self._index_flat[entries]]

    def _primitives_at(self, theta: np.ndarray) -> np.ndarray:
        """``primitives(theta)`` of a checked theta, the last one's kept (a learner's step
        asks for them three times: the table, and two pull-backs)."""
        owner = self._primitives_owner
        theta = np.asarray(theta, dtype=np.float64)
        key = theta.tobytes()
        last = owner._last_primitives
        if last is None or last[0] != key:
            primitives = owner.primitives(theta)
            primitives.flags.writeable = False  # shared by the callers
            last = (key, primitives)
            owner._last_primitives = last
        return last[1]

    def transitions(self, theta: np.ndarray) -> SparseTransitions:
        return SparseTransitions(self.next_states, self.probabilities(theta))

    def pullback(
        self, theta: np.ndarray, d_probabilities: np.ndarray, rule: str = "exact"
    ) -> np.ndarray:
        """Gradient with respect to theta of a function whose gradient with respect to the
        sparse transition probabilities is ``d_probabilities`` (shape (S, A, M)).

        ``rule="authors"`` gives the paper authors' update where their model space has one
        that is not the exact gradient (``outcomes``; farming): each entry e of probability
        T_e with weight w_e = dL/dT_e * T_e adds w_e * 2 d ln p(theta)[k] for a success and
        w_e * (d ln(1 - p[k]) - d ln p[k]) for a failure. Elsewhere it is the exact gradient."""
        theta = self.check_parameters(theta)
        d_probabilities = check_shape(
            "gradient on transition probabilities", d_probabilities, self.next_states.shape
        )
        check_gradient_rule(rule)
        d_moved = d_probabilities.reshape(-1)[self.flat_parametric_entries]
        if rule == "authors" and self.outcomes is not None:
            p = self._primitives_at(theta)
            moved = self.flat_parametric_entries
            k = self._parametric_index
            weights = d_moved * _outcome_factors(
                self.outcomes.reshape(-1)[moved], self._entry_probabilities(p, moved), p[k]
            )
        else:
            # The entries theta moves, in table order (the others' coefficients are 0).
            weights = self._parametric_coef * d_moved
        return self._pull_back_moved(theta, weights)

    def _pull_back_moved(self, theta: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """The gradient with respect to a checked theta from ``weights`` on the entries theta
        moves (``flat_parametric_entries``, in table order): each adds to its primitive's."""
        d_p = np.bincount(self._parametric_index, weights=weights, minlength=self.num_primitives)
        return self.primitives_pullback(theta, d_p)

    def pullback_dense(self, theta: np.ndarray, d_transitions: np.ndarray) -> np.ndarray:
        """Pull back a gradient on the dense (S, A, S) transition array to theta."""
        s, a, _ = self.next_states.shape
        d_transitions = check_shape("gradient on transitions", d_transitions, (s, a, s))
        d_probabilities = np.take_along_axis(d_transitions, self.next_states, axis=2)
        return self.pullback(theta, d_probabilities)

    def observe(self, observed: np.ndarray | ObservedTransitions) -> ObservedTransitions:
        """Observed (state, action, next_state) rows checked once and matched to the table's
        entries, for ``transition_log_likelihood`` at many theta (a learner's update)."""
        if isinstance(observed, ObservedTransitions):
            return observed
        observed = np.asarray(observed, dtype=np.int64).reshape(-1, 3)
        s, a, s2 = observed.T
        if np.any((s < 0) | (s >= self.num_states) | (s2 < 0) | (s2 >= self.num_states)):
            raise ValueError("observed transition has a state out of range")
        if np.any((a < 0) | (a >= self.num_actions)):
            raise ValueError("observed transition has an action out of range")
        match = self.next_states[s, a] == s2[:, None]  # (N, M)
        rows, columns = np.nonzero(match)  # row by row, entries in table order
        entries = ((s[rows] * self.num_actions + a[rows]) * self.width + columns).astype(np.int64)
        rows = rows.astype(np.int64)
        places = self._moved_place[entries]
        moved = places >= 0
        if self.outcomes is not None:
            # The authors' update: one term per observed transition through a parametric
            # row, from its first parametric entry (``transition_log_likelihood``).
            outcomes = self.outcomes.reshape(-1)[entries]
            parametric = outcomes != 0
            _, first = np.unique(rows[parametric], return_index=True)
            firsts = entries[parametric][first]
            first_outcomes, first_index = outcomes[parametric][first], self._index_flat[firsts]
        else:
            first_outcomes = first_index = np.empty(0, dtype=np.int64)
        return ObservedTransitions(
            observed,
            entries,
            rows,
            const=self._const_flat[entries],
            coef=self._coef_flat[entries],
            index=self._index_flat[entries],
            moved_places=places[moved],
            moved_rows=rows[moved],
            first_outcomes=first_outcomes,
            first_index=first_index,
        )

    def transition_log_likelihood(
        self,
        theta: np.ndarray,
        observed: np.ndarray | ObservedTransitions,
        rule: str = "exact",
    ) -> tuple[float, np.ndarray]:
        """Sum over observed (state, action, next_state) rows of ln T_theta(s, a, s'), and its
        gradient with respect to theta. A transition the model space cannot produce is an error.

        With ``rule="authors"`` the gradient is the paper authors' update where their model
        space has one (``outcomes``; farming): each observed transition through a parametric
        row adds 2 d ln p[k] if it was a success, d ln(1 - p[k]) - d ln p[k] if a failure.
        The value is the exact log-likelihood either way."""
        observed = self.observe(observed)
        check_gradient_rule(rule)
        count = len(observed.rows)
        if count == 0:
            return 0.0, np.zeros(self.num_parameters)
        # The observed entries' probabilities only (the table's, entry by entry).
        theta = self.check_parameters(theta)
        p = self._primitives_at(theta)
        entry_probability = observed.const + observed.coef * p[observed.index]
        # T(s, a, s') sums the row's entries that lead to s' (a next state may repeat).
        row_probability = np.bincount(
            observed.entry_rows, weights=entry_probability, minlength=count
        )
        rounded = row_probability <= 0.0
        if rounded.any():
            # A row the model space can give some probability (an entry theta moves, or a
            # fixed one above 0) that rounds to 0 at this theta: a saturated logit, p within
            # 2^-53 of 1, leaves 1 - p = 0 (farming's logits reach +-50). It counts as the
            # least normal probability; the rest are impossible whatever theta.
            possible = (observed.coef != 0.0) | (observed.const > 0.0)
            reachable = np.bincount(observed.entry_rows[possible], minlength=count) > 0
            if not np.all(reachable[rounded]):
                bad = int(np.flatnonzero(rounded & ~reachable)[0])
                raise ValueError(
                    f"observed transition {tuple(int(x) for x in observed.rows[bad])} is "
                    "impossible under the model space"
                )
            row_probability = np.where(rounded, LEAST_PROBABILITY, row_probability)
        value = float(np.log(row_probability).sum())
        if rule == "authors" and self.outcomes is not None:
            # One term per observed transition, from its first parametric entry (``observe``).
            # The planner's rule with weight w = 1 for each transition (T_e / p read as 1 / p).
            k = observed.first_index
            pk = p[k]
            terms = _outcome_factors(observed.first_outcomes, np.ones_like(pk), pk)
            d_p = np.bincount(k, weights=terms, minlength=self.num_primitives)
            return value, self.primitives_pullback(theta, d_p)
        # d ln T / dT = 1 / T; a row rounded to 0 adds nothing (its entries' derivatives
        # through theta round to 0 as well, and 1 / LEAST_PROBABILITY would blow them up).
        # Summed at the entries theta moves only, each entry's terms in the order of the
        # observed rows, as over the whole table (whose other entries the pull-back drops).
        weights = np.where(rounded, 0.0, 1.0 / row_probability)
        d_moved = np.bincount(
            observed.moved_places,
            weights=weights[observed.moved_rows],
            minlength=self.flat_parametric_entries.size,
        )
        return value, self._pull_back_moved(theta, self._parametric_coef * d_moved)


GRADIENT_RULES = ("authors", "exact")


# An observed transition's probability where the model space's rounds to 0 (its ln: -708.4).
LEAST_PROBABILITY = float(np.finfo(np.float64).tiny)


def check_gradient_rule(rule: str) -> None:
    if rule not in GRADIENT_RULES:
        raise ValueError(
            f"dynamics_gradient must be one of {', '.join(map(repr, GRADIENT_RULES))}, got {rule!r}"
        )


def _outcome_factors(outcomes: np.ndarray, t: np.ndarray, pk: np.ndarray) -> np.ndarray:
    """The authors' term per unit of dL/dT_e on p[k] for entries of probability ``t``:
    T_e * 2 / p for a success, T_e * (-1 / (1 - p) - 1 / p) for a failure; T_e / p and
    T_e / (1 - p) are taken as 1 where their denominator is 0 (their limit for the entries
    whose probability is that denominator)."""
    ones = np.ones_like(t)
    over_p = np.divide(t, pk, out=ones.copy(), where=pk > 0.0)
    over_q = np.divide(t, 1.0 - pk, out=ones, where=pk < 1.0)
    return np.where(outcomes > 0, 2.0 * over_p, -over_q - over_p)


@dataclass(frozen=True)
class MovedEntries:
    """The entries of a model's table that theta moves (``flat_parametric_entries``, in table
    order): each one's probability is ``const + coef * p[index]`` at primitives p, and its
    ``outcome`` is the authors' farming rule's (+1 a success, -1 a failure; 0 without the rule).
    What a compiled step on theta reads of the model."""

    const: np.ndarray
    coef: np.ndarray
    index: np.ndarray
    outcomes: np.ndarray


@dataclass(frozen=True)
class ObservedTransitions:
    """Observed transitions matched to a model space's table (``TransitionModel.observe``),
    with what its likelihood reads of the model at every theta."""

    rows: np.ndarray  # (N, 3) state, action, next state
    entries: np.ndarray  # flat table entries (s * A + a) * M + m whose next state is the row's
    entry_rows: np.ndarray  # the observed row of each entry
    # Each entry's probability is const + coef * p[index] at primitives p.
    const: np.ndarray
    coef: np.ndarray
    index: np.ndarray
    # The entries theta moves: their places in ``flat_parametric_entries`` and their rows.
    moved_places: np.ndarray
    moved_rows: np.ndarray
    # The authors' farming update: each parametric row's first entry's outcome and primitive.
    first_outcomes: np.ndarray
    first_index: np.ndarray


class SigmoidModel(TransitionModel):
    """One logit per parameter; the primitive is sigmoid(theta) (navigation: a move into cell i
    fails with probability sigmoid(theta_i))."""

    @property
    def num_primitives(self) -> int:
        return self.num_parameters

    def primitives(self, theta: np.ndarray) -> np.ndarray:
        return 0.5 * (1.0 + np.tanh(0.5 * theta))  # stable sigmoid

    def primitives_pullback(self, theta: np.ndarray, d_primitives: np.ndarray) -> np.ndarray:
        p = self._primitives_at(theta)
        return d_primitives * p * (1.0 - p)


class SoftmaxRowsModel(TransitionModel):
    """Parameters form a (groups, choices) matrix; each row is a softmax (gravity: per colour
    over four gravities; farming: per machine over three terrains)."""

    def __init__(self, *args: Any, groups: int, choices: int, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if groups * choices != self.num_parameters:
            raise ValueError("groups * choices must equal the number of parameters")
        self.groups = groups
        self.choices = choices

    @property
    def num_primitives(self) -> int:
        return self.num_parameters

    def primitives(self, theta: np.ndarray) -> np.ndarray:
        logits = theta.reshape(self.groups, self.choices)
        z = np.exp(logits - logits.max(axis=1, keepdims=True))
        return (z / z.sum(axis=1, keepdims=True)).ravel()

    def primitives_pullback(self, theta: np.ndarray, d_primitives: np.ndarray) -> np.ndarray:
        p = self._primitives_at(theta).reshape(self.groups, self.choices)
        g = d_primitives.reshape(self.groups, self.choices)
        return (p * (g - (g * p).sum(axis=1, keepdims=True))).ravel()
