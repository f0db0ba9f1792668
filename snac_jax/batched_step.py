"""A batch of worlds stepped with gymnax's auto-reset, resetting only the worlds that ended.

`SNACEnv.step_batch` delegates here. Its outputs equal `jax.vmap(env.step, in_axes=(0, 0, 0,
None))` bit for bit (tests/test_step_batch.py checks it on every kind of task); only the way
the auto-reset is computed differs.

Why it exists: the auto-reset of `vmap(step)` selects, for every world and every step, between
its stepped state and a reset state: a pass over every grid and design, which is most of a
step's memory traffic when the step itself touches one cell. Here the worlds whose episode
ended (a few per step out of thousands) are reset one by one in a loop and written into the
batch in place; the others are never copied.

Use it for a batch that jit does not split across devices (one device, or each device's share
inside `shard_map`, as `snac_jax.rollout` does): with jit's sharding propagation, writing single
worlds into a sharded batch makes XLA gather the batch. `vmap(env.step)` is right everywhere.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp

from snac_jax.state import EnvParams, EnvState

if TYPE_CHECKING:
    from snac_jax.env import SNACEnv


def step_batch(
    env: SNACEnv, keys: jax.Array, states: EnvState, actions: jax.Array, params: EnvParams
) -> tuple[jax.Array, EnvState, jax.Array, jax.Array, jax.Array, dict[str, Any]]:
    """One step of every world of the batch (leading axis), with `env.step`'s outputs and info
    keys; `params` is shared by the batch. Traced inside the caller's jit."""
    _, stepped, reward, terminated, info = jax.vmap(env.step_env, in_axes=(0, 0, 0, None))(keys, states, actions, params)
    truncated = jax.vmap(env.is_truncated, in_axes=(0, None))(stepped, params)
    done = terminated | truncated
    ended = jnp.nonzero(done, size=done.shape[0], fill_value=0)[0]

    def reset_one(i, states):
        world = ended[i]
        _, fresh = env.reset_env(keys[world], params)
        return jax.tree.map(
            lambda batch, leaf: jax.lax.dynamic_update_index_in_dim(batch, leaf.astype(batch.dtype), world, 0), states, fresh
        )

    states = jax.lax.fori_loop(0, jnp.sum(done, dtype=jnp.int32), reset_one, stepped)
    observe = jax.vmap(env.get_obs, in_axes=(0, None))
    info = {**info, "terminated": terminated, "truncated": truncated, "final_observation": observe(stepped, params)}
    return observe(states, params), states, reward, terminated, truncated, info
