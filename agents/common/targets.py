"""Learning targets, each a pure function over time-major arrays, each checked against a
hand-computed example in the tests: GAE for PPO, n-step returns for the replay Q-learners, Q(lambda)
returns for PQN, the projection of a discounted return distribution onto a fixed support for the
distributional one (Rainbow); and the values at truncations that PPO's and PQN's targets bootstrap from."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

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


def n_step_returns(
    rewards: jax.Array, dones: jax.Array, gamma: float, n: int, length: int
) -> tuple[jax.Array, jax.Array]:
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


def n_step_targets(
    rewards: jax.Array, dones: jax.Array, values: jax.Array, gamma: float, n: int, length: int
) -> jax.Array:
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


def q_lambda(
    rewards: jax.Array,
    next_values: jax.Array,
    final_values: jax.Array,
    terminated: jax.Array,
    truncated: jax.Array,
    gamma: float,
    td_lambda: float,
) -> jax.Array:
    """Q(lambda) returns over time-major `(T, ...)` arrays (PQN's targets, Gallici et al. 2024).

    `next_values[t]` is the greedy value `max_a Q` of the observation after step t as the rollout
    saw it: the next row's observation, and for the last row the one the rollout stopped at.
    Where the episode ended at t that observation starts the next episode and is ignored.
    `final_values[t]` is the value of the episode's last observation (before the auto-reset),
    read only where `truncated[t]`. With `G[T] = next_values[T-1]`:

        terminated[t]:  G[t] = r[t]                                   (nothing lies beyond)
        truncated[t]:   G[t] = r[t] + gamma * final_values[t]          (the trace is cut)
        otherwise:      G[t] = r[t] + gamma * ((1 - lambda) * next_values[t] + lambda * G[t+1])

    A step both terminated and truncated counts as terminated.
    """
    bootstrap_if_ended = jnp.where(terminated, 0.0, final_values)
    ended = terminated | truncated

    def backward(following, step):
        reward, next_value, end_value, done = step
        mixed = (1.0 - td_lambda) * next_value + td_lambda * following
        ret = reward + gamma * jnp.where(done, end_value, mixed)
        return ret, ret

    _, returns = jax.lax.scan(
        backward, next_values[-1], (rewards, next_values, bootstrap_if_ended, ended), reverse=True
    )
    return returns


def truncation_values(
    score: Callable[[jax.Array, Any], jax.Array],
    truncated: jax.Array,
    final_obs: Any,
    carry_after: jax.Array,
    per_world: int,
) -> jax.Array:
    """`(T, B)` values `score(carry (N, C), obs (N, O)) -> (N,)` of the final observations where
    `truncated (T, B)`, 0 elsewhere; `final_obs (T, B, O)` and `carry_after (T, B, C)` (the
    recurrent state that saw the episode) per step. `final_obs` may be a pytree of `(T, B, ...)`
    arrays (a critic's other inputs beside the observation); `score` then receives it per step.
    `per_world`: the most truncations one world can have in T steps (`ObsLayout.max_truncations`).

    Why not score every step: truncations are rare (one per step limit per world), and a
    forward pass over all `T * B` final observations costs as much as the rollout's own. The
    truncations are gathered, `per_world * B` at most, and scored. The bound is static, so no
    branch picks a path at run time (under `vmap` over seeds both branches of a `cond` run); a
    batch past it (a step limit shorter than the one the bound was made for) reads NaN, loudly.
    """
    t, n = truncated.shape
    size = min(per_world * n, t * n)
    truncated = truncated.reshape(-1)
    final_obs = jax.tree.map(lambda x: x.reshape((t * n,) + x.shape[2:]), final_obs)
    carry_after = carry_after.reshape(t * n, -1)
    (index,) = jnp.nonzero(truncated, size=size, fill_value=0)
    chosen = jax.tree.map(lambda x: x[index], final_obs)
    count = truncated.sum()
    values = jnp.where(jnp.arange(size) < count, score(carry_after[index], chosen), 0.0)
    values = jnp.zeros((t * n,), values.dtype).at[index].add(values)
    return jnp.where(count > size, jnp.nan, values).reshape(t, n)
