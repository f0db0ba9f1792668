"""Batched rollouts: many worlds stepped in one jitted `lax.scan`, with gymnax auto-reset.

`random_rollout` runs a uniform-random policy; with a device mesh (`snac_jax.devices`) each
device steps its own share of the worlds, so every CPU core works.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from flax import struct

from snac_jax import batched_step, devices, memory, threefry
from snac_jax.env import SNACEnv
from snac_jax.state import EnvParams


@struct.dataclass
class EpisodeStats:
    """Running statistics of the episodes that ended during a rollout."""

    episodes: jax.Array  # int32, episodes ended
    iou_sum: jax.Array  # float32
    iou_min: jax.Array  # float32 (1.0 when none ended)
    iou_max: jax.Array  # float32 (0.0 when none ended)

    @classmethod
    def empty(cls) -> EpisodeStats:
        return cls(
            episodes=jnp.zeros((), jnp.int32), iou_sum=jnp.zeros(()), iou_min=jnp.ones(()), iou_max=jnp.zeros(())
        )

    def add(self, done: jax.Array, final_iou: jax.Array) -> EpisodeStats:
        return EpisodeStats(
            episodes=self.episodes + jnp.sum(done),
            iou_sum=self.iou_sum + jnp.sum(jnp.where(done, final_iou, 0.0)),
            iou_min=jnp.minimum(self.iou_min, jnp.min(jnp.where(done, final_iou, 1.0))),
            iou_max=jnp.maximum(self.iou_max, jnp.max(jnp.where(done, final_iou, 0.0))),
        )

    def combine(self) -> EpisodeStats:
        """Merge statistics stacked along a leading axis (one entry per device)."""
        return EpisodeStats(
            episodes=jnp.sum(self.episodes),
            iou_sum=jnp.sum(self.iou_sum),
            iou_min=jnp.min(self.iou_min),
            iou_max=jnp.max(self.iou_max),
        )

    @property
    def iou_mean(self) -> float:
        return float(self.iou_sum) / max(int(self.episodes), 1)


def uniform_actions(key: jax.Array, num_envs: int, num_actions: int) -> jax.Array:
    """One uniform action per env from one random word each (`bits % A`, biased by < A / 2**32;
    `jax.random.randint` is exact but draws two words per action)."""
    return (threefry.bits(key, num_envs) % jnp.uint32(num_actions)).astype(jnp.int32)


def _rollout(
    key: jax.Array, env: SNACEnv, params: EnvParams, num_envs: int, num_steps: int, reset: str
) -> EpisodeStats:
    """`num_envs` worlds on one device: per step, one hash per env for the env key, one for the
    action and one inside the step, stepped by `env.step_batch` with the concrete `reset`
    strategy (the same worlds whichever it is)."""
    key_reset, key_run = jax.random.split(key)
    _, states = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key_reset, num_envs), params)

    def step(keys, states, actions, params):
        return env.step_batch(keys, states, actions, params, reset=reset)

    def body(carry, step_key):
        states, stats = carry
        key_act, key_step = jax.random.split(step_key)
        actions = uniform_actions(key_act, num_envs, env.num_actions)
        _, states, _, terminated, truncated, info = step(threefry.split(key_step, num_envs), states, actions, params)
        return (states, stats.add(terminated | truncated, info["final_iou"])), None

    (_, stats), _ = jax.lax.scan(body, (states, EpisodeStats.empty()), jax.random.split(key_run, num_steps))
    return stats


def require_rollout_memory(env: SNACEnv, params: EnvParams, num_envs: int) -> None:
    """`ValueError` with the estimate if `num_envs` worlds would not fit: every world's state
    and observation, in the scan's carry and the step's copy."""
    obs, state = jax.eval_shape(env.reset, jax.random.key(0), params)
    memory.require(f"{num_envs:,} worlds", 2 * num_envs * memory.tree_bytes((obs, state)), "use fewer worlds")


@partial(jax.jit, static_argnames=("env", "num_envs", "num_steps", "mesh", "reset"))
def random_rollout(
    key: jax.Array, env: SNACEnv, params: EnvParams, num_envs: int, num_steps: int, mesh=None, reset: str = "auto"
) -> EpisodeStats:
    """`num_envs` worlds under a uniform-random policy for `num_steps` steps each.

    The worlds are stepped with `env.step_batch` and its auto-reset strategy `reset` (`"loop"`,
    `"select"` or `"auto"`: the backend's own, see `snac_jax.batched_step`): the same worlds and
    statistics whichever it is.

    With `mesh` (`snac_jax.devices.env_mesh()`), the worlds are split evenly over its devices,
    each device running its own scan from its own key; `num_envs` must be a multiple of the
    device count. The same key gives different (equally distributed) worlds for another mesh.
    A `num_envs` whose estimated memory exceeds the device's is refused while tracing.
    """
    reset = batched_step.resolve_reset(reset)
    require_rollout_memory(env, params, num_envs)
    if mesh is None or mesh.devices.size == 1:
        return _rollout(key, env, params, num_envs, num_steps, reset)
    devices.check_divisible(num_envs, mesh)
    per_device = num_envs // mesh.devices.size

    def shard(device_key, params):
        stats = _rollout(device_key[0], env, params, per_device, num_steps, reset)
        return jax.tree.map(lambda x: x[None], stats)

    run = jax.shard_map(
        shard, mesh=mesh, in_specs=(devices.ENVS, jax.sharding.PartitionSpec()), out_specs=devices.ENVS, check_vma=False
    )
    return run(jax.random.split(key, mesh.devices.size), params).combine()
