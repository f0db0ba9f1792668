"""Batched rollouts: many worlds stepped in one jitted `lax.scan`, with gymnax auto-reset."""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from flax import struct

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
    def empty(cls) -> "EpisodeStats":
        return cls(jnp.zeros((), jnp.int32), jnp.zeros(()), jnp.ones(()), jnp.zeros(()))

    def add(self, done: jax.Array, final_iou: jax.Array) -> "EpisodeStats":
        return EpisodeStats(
            episodes=self.episodes + jnp.sum(done),
            iou_sum=self.iou_sum + jnp.sum(jnp.where(done, final_iou, 0.0)),
            iou_min=jnp.minimum(self.iou_min, jnp.min(jnp.where(done, final_iou, 1.0))),
            iou_max=jnp.maximum(self.iou_max, jnp.max(jnp.where(done, final_iou, 0.0))),
        )

    @property
    def iou_mean(self) -> float:
        return float(self.iou_sum) / max(int(self.episodes), 1)


@partial(jax.jit, static_argnames=("env", "num_envs", "num_steps"))
def random_rollout(key: jax.Array, env: SNACEnv, params: EnvParams, num_envs: int, num_steps: int) -> EpisodeStats:
    """`num_envs` worlds under a uniform-random policy for `num_steps` steps each."""
    key_reset, key_run = jax.random.split(key)
    _, states = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key_reset, num_envs), params)
    step = jax.vmap(env.step, in_axes=(0, 0, 0, None))

    def body(carry, step_key):
        states, stats = carry
        key_act, key_step = jax.random.split(step_key)
        actions = jax.random.randint(key_act, (num_envs,), 0, env.num_actions)
        _, states, _, terminated, truncated, info = step(jax.random.split(key_step, num_envs), states, actions, params)
        return (states, stats.add(terminated | truncated, info["final_iou"])), None

    (_, stats), _ = jax.lax.scan(body, (states, EpisodeStats.empty()), jax.random.split(key_run, num_steps))
    return stats
