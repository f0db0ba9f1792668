"""Learning targets, each a pure function over time-major arrays, each checked against a
hand-computed example in the tests: GAE for PPO, n-step returns for the Q-learners, and the
projection of a discounted return distribution onto a fixed support for distributional ones."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def gae(
    rewards: jax.Array,
    values: jax.Array,
    next_values: jax.Array,
    terminated: jax.Array,
    done: jax.Array,
    gamma: float,
    gae_lambda: float,
) -> tuple[jax.Array, jax.Array]:
    """Generalised advantage estimation over time-major `(T, ...)` arrays.

    `next_values[t]` is the value of the state after step t: the next observation's, or the
    final observation's where the episode ended at t. A termination bootstraps nothing; a
    truncation bootstraps from `next_values[t]`; either ends the advantage trace (`done`).
    Returns `(advantages, value targets)`.
    """
    deltas = rewards + gamma * (1.0 - terminated) * next_values - values

    def backward(advantage, step):
        delta, ended = step
        advantage = delta + gamma * gae_lambda * (1.0 - ended) * advantage
        return advantage, advantage

    _, advantages = jax.lax.scan(
        backward, jnp.zeros_like(deltas[-1]), (deltas, done.astype(deltas.dtype)), reverse=True
    )
    return advantages, advantages + values


def n_step_returns(rewards: jax.Array, dones: jax.Array, gamma: float, n: int, length: int) -> tuple[jax.Array, jax.Array]:
    """`(reward sums, bootstrap discounts)` of n-step returns for the first `length` steps of
    time-major `(length + n, ...)` arrays: the target of step t is `sums[t] + discounts[t] * value
    of the observation n steps on`. `dones[t]` means the episode ended at step t, so neither later
    rewards nor a bootstrap count past it (its discount is 0)."""
    target = jnp.zeros_like(rewards[:length])
    alive = jnp.ones_like(rewards[:length])
    for i in range(n):
        target = target + (gamma**i) * alive * rewards[i : i + length]
        alive = alive * (1.0 - dones[i : i + length].astype(rewards.dtype))
    return target, (gamma**n) * alive


def n_step_targets(rewards: jax.Array, dones: jax.Array, values: jax.Array, gamma: float, n: int, length: int) -> jax.Array:
    """n-step return targets for the first `length` steps of time-major `(length + n, ...)` arrays.

    `values[t]` is the bootstrap value of the observation at t; `dones[t]` means the episode ended
    at step t, so neither later rewards nor a bootstrap value count past it.
    """
    returns, discounts = n_step_returns(rewards, dones, gamma, n, length)
    return returns + discounts * values[n : n + length]


def categorical_projection(support: jax.Array, probs: jax.Array, returns: jax.Array, discounts: jax.Array) -> jax.Array:
    """The distribution of `returns + discounts * Z`, where Z takes the values of `support`
    (evenly spaced atoms, V_min first) with probabilities `probs (..., atoms)`, projected back
    onto `support` (C51, Bellemare et al. 2017): each shifted atom is clipped to [V_min, V_max]
    and its mass split between the two atoms beside it in proportion to closeness. A discount of
    0 (the episode ended) puts all mass at `returns`. `returns` and `discounts` have shape `...`."""
    v_min, v_max, atoms = support[0], support[-1], support.shape[0]
    shifted = jnp.clip(returns[..., None] + discounts[..., None] * support, v_min, v_max)
    position = (shifted - v_min) / ((v_max - v_min) / (atoms - 1))  # (..., atoms) in [0, atoms - 1]
    # Target atom i receives p_j * max(0, 1 - |position_j - i|) from each source atom j: a
    # matrix-vector product, which XLA's CPU backend runs far faster than a broadcast multiply and sum.
    share = jnp.clip(1.0 - jnp.abs(position[..., None, :] - jnp.arange(atoms, dtype=position.dtype)[:, None]), 0.0, 1.0)
    return jnp.einsum("...ij,...j->...i", share, probs)
