"""Learning targets, each a pure function over time-major arrays, each checked against a
hand-computed example in the tests: GAE for PPO, n-step returns for the Q-learners."""

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


def n_step_targets(rewards: jax.Array, dones: jax.Array, values: jax.Array, gamma: float, n: int, length: int) -> jax.Array:
    """n-step return targets for the first `length` steps of time-major `(length + n, ...)` arrays.

    `values[t]` is the bootstrap value of the observation at t; `dones[t]` means the episode ended
    at step t, so neither later rewards nor a bootstrap value count past it.
    """
    target = jnp.zeros_like(rewards[:length])
    alive = jnp.ones_like(rewards[:length])
    for i in range(n):
        target = target + (gamma**i) * alive * rewards[i : i + length]
        alive = alive * (1.0 - dones[i : i + length].astype(rewards.dtype))
    return target + (gamma**n) * alive * values[n : n + length]
