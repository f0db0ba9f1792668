"""A batch of worlds stepped with gymnax's auto-reset, by the reset strategy that suits the backend.

`SNACEnv.step_batch` delegates here. Whatever the strategy, its outputs equal
`jax.vmap(env.step, in_axes=(0, 0, 0, None))` bit for bit (tests/test_step_batch.py checks it on
every kind of task); only the way the auto-reset is computed differs:

- `"loop"`: the worlds whose episode ended (a few per step out of thousands) are reset one by one
  in a `fori_loop` and written into the batch in place; the others are never copied. On a CPU
  this is the fast path: the select below is a pass over every grid and design, most of a step's
  memory traffic when the step itself touches one cell. On a GPU each trip of that loop is a
  chain of tiny kernels launched one after another, so the loop is the slow path there.
- `"select"`: every world's fresh state is computed and selected where its episode ended, as
  gymnax, JaxMARL and Brax do: one fused, data-parallel pass. For a task with one design and no
  landmarks the fresh state does not depend on the key, so under `vmap` it stays unbatched and
  the select broadcasts one cached first state (Brax's trick) without computing a reset per world.
- `"auto"`: `"loop"` on a CPU, `"select"` on a GPU or TPU (the backend JAX computes on by default).

Use `"loop"` for a batch that jit does not split across devices (one device, or each device's
share inside `shard_map`, as `snac_jax.rollout` does): with jit's sharding propagation, writing
single worlds into a sharded batch makes XLA gather the batch. `"select"` is right everywhere.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp

from snac_jax.state import EnvParams, EnvState

if TYPE_CHECKING:
    from snac_jax.env import SNACEnv

RESET_STRATEGIES = ("auto", "loop", "select")
"""The values of `reset=` wherever a batch is stepped (`env.step_batch`, `snac_jax.rollout`,
`snac rollout --reset`, the Gymnasium vector env, the benchmarks)."""


def check_reset(reset: Any) -> str:
    """`reset` if it names a strategy, else a one-line `ValueError` naming the allowed values."""
    if not isinstance(reset, str) or reset not in RESET_STRATEGIES:
        raise ValueError(f"reset must be one of {', '.join(RESET_STRATEGIES)}, got {reset!r}")
    return reset


def resolve_reset(reset: str, backend: str | None = None) -> str:
    """The concrete strategy (`"loop"` or `"select"`) for `reset` on `backend` (default: the
    backend JAX computes on by default, `jax.default_backend()`)."""
    if check_reset(reset) != "auto":
        return reset
    return "loop" if (backend or jax.default_backend()) == "cpu" else "select"


def step_batch(
    env: SNACEnv, keys: jax.Array, states: EnvState, actions: jax.Array, params: EnvParams, reset: str = "loop"
) -> tuple[jax.Array, EnvState, jax.Array, jax.Array, jax.Array, dict[str, Any]]:
    """One step of every world of the batch (leading axis), with `env.step`'s outputs and info
    keys; `params` is shared by the batch. `reset` is `"loop"` or `"select"` (resolve `"auto"`
    with `resolve_reset` before tracing). Traced inside the caller's jit."""
    if resolve_reset(reset) == "select":
        return jax.vmap(env.step, in_axes=(0, 0, 0, None))(keys, states, actions, params)
    _, stepped, reward, terminated, info = jax.vmap(env.step_env, in_axes=(0, 0, 0, None))(
        keys, states, actions, params
    )
    truncated = jax.vmap(env.is_truncated, in_axes=(0, None))(stepped, params)
    done = terminated | truncated
    ended = jnp.nonzero(done, size=done.shape[0], fill_value=0)[0]

    def reset_one(i, states):
        world = ended[i]
        _, fresh = env.reset_env(keys[world], params)
        return jax.tree.map(
            lambda batch, leaf: jax.lax.dynamic_update_index_in_dim(batch, leaf.astype(batch.dtype), world, 0),
            states,
            fresh,
        )

    states = jax.lax.fori_loop(0, jnp.sum(done, dtype=jnp.int32), reset_one, stepped)
    observe = jax.vmap(env.get_obs, in_axes=(0, None))
    info = {**info, "terminated": terminated, "truncated": truncated, "final_observation": observe(stepped, params)}
    return observe(states, params), states, reward, terminated, truncated, info
