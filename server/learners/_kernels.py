"""Compiled inner loops of soft value iteration (forward and reverse pass).

The transitions are the padded sparse layout of ``SparseTransitions`` flattened to rows
``s * A + a`` with ``width`` entries each. Written as plain loops for numba: the NumPy version
spent most of its time in call overhead on small arrays (about 100 us per backup on flip); these
loops do the same arithmetic without it.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, fastmath=False)
def soft_forward(
    next_flat: np.ndarray,
    probs_flat: np.ndarray,
    width: int,
    rewards: np.ndarray,
    beta: float,
    horizon: int,
    num_actions: int,
    keep_trace: bool,
):
    num_tasks, num_states = rewards.shape
    q = np.empty((num_tasks, num_states, num_actions))
    trace_len = horizon if keep_trace else 0
    values = np.empty((trace_len, num_tasks, num_states))
    jacobians = np.empty((trace_len, num_tasks, num_states, num_actions))
    previous = np.zeros(num_states)
    current = np.zeros(num_states)
    row = np.empty(num_actions)
    weights = np.empty(num_actions)
    for k in range(num_tasks):
        for t in range(horizon):
            last = t == horizon - 1
            for s in range(num_states):
                r = rewards[k, s]
                best = -np.inf
                for a in range(num_actions):
                    acc = r
                    if t > 0:
                        base = (s * num_actions + a) * width
                        for m in range(width):
                            acc += probs_flat[base + m] * previous[next_flat[base + m]]
                    row[a] = acc
                    if acc > best:
                        best = acc
                if last:
                    # Q_horizon is the output; its Boltzmann value is never used.
                    for a in range(num_actions):
                        q[k, s, a] = row[a]
                    continue
                total = 0.0
                for a in range(num_actions):
                    # exp(0) = 1 for the best action(s): skip the call.
                    w = 1.0 if row[a] == best else np.exp(beta * (row[a] - best))
                    weights[a] = w
                    total += w
                value = 0.0
                for a in range(num_actions):
                    weights[a] /= total
                    value += weights[a] * row[a]
                current[s] = value
                if keep_trace:
                    values[t, k, s] = value
                    for a in range(num_actions):
                        jacobians[t, k, s, a] = weights[a] * (1.0 + beta * (row[a] - value))
            for s in range(num_states):
                previous[s] = current[s]
        for s in range(num_states):
            previous[s] = 0.0
    return q, values, jacobians


@njit(cache=True, fastmath=False)
def soft_backward(
    next_flat: np.ndarray,
    probs_flat: np.ndarray,
    width: int,
    values: np.ndarray,
    jacobians: np.ndarray,
    d_q: np.ndarray,
    horizon: int,
    need_transitions: bool,
):
    num_tasks, num_states, num_actions = d_q.shape
    d_reward = np.zeros((num_tasks, num_states))
    d_probs = np.zeros(next_flat.shape[0] if need_transitions else 0)
    g = np.empty((num_states, num_actions))
    g_v = np.empty(num_states)
    for k in range(num_tasks):
        for s in range(num_states):
            for a in range(num_actions):
                g[s, a] = d_q[k, s, a]
        for t in range(horizon, 0, -1):
            for s in range(num_states):
                acc = 0.0
                for a in range(num_actions):
                    acc += g[s, a]
                d_reward[k, s] += acc
            if t == 1:
                break
            for s in range(num_states):
                g_v[s] = 0.0
            for s in range(num_states):
                for a in range(num_actions):
                    gsa = g[s, a]
                    if gsa == 0.0:
                        continue
                    base = (s * num_actions + a) * width
                    for m in range(width):
                        j = base + m
                        nxt = next_flat[j]
                        g_v[nxt] += probs_flat[j] * gsa
                        if need_transitions:
                            d_probs[j] += gsa * values[t - 2, k, nxt]
            for s in range(num_states):
                for a in range(num_actions):
                    g[s, a] = g_v[s] * jacobians[t - 2, k, s, a]
    return d_reward, d_probs


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
