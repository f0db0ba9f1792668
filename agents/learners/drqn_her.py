"""DRQN + hindsight relabelling (paper: "the transitions ... relabeled with D replaced by the grid
at the terminal step; both stored"), on top of `agents.learners.drqn`.

Each stored step also records where its brick landed and the cell's height (`drop_record`), and
when a world's episode ends its final grid goes into a small ring per world (`FinalGrids`). A
sampled window read as the relabelled copy (a `hindsight_fraction` of each batch) gets its
rewards recomputed against its episode's final grid with the environment's own
`snac_jax.transition.drop_reward`, and on dynamic tasks the design part of its observations
replaced by that grid. Steps of an episode that has not ended yet have no relabelled copy yet and
are left out of that window's loss. Keeping one grid per episode instead of a second copy of every
step makes the relabelled copy nearly free in memory.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import ClassVar

import jax
import jax.numpy as jnp
from flax import struct

from agents.common.inputs import episode_min_steps
from agents.common.offpolicy import RunnerState, Step, Worlds
from agents.learners.drqn import DRQN, DRQNConfig
from agents.training.config import option
from snac_jax.config import EnvConfig
from snac_jax.transition import drop_reward


@dataclasses.dataclass(frozen=True)
class DRQNHERConfig(DRQNConfig):
    algorithm: ClassVar[str] = "drqn-her"
    paper_method: ClassVar[str] = "drqn_her"

    hindsight_fraction: float = option(0.5, "share of sampled sequences read as the relabelled copy", low=0, high=1)


@struct.dataclass
class HindsightStep(Step):
    world: jax.Array  # int32, the world (buffer row) the step came from
    episode: jax.Array  # int32, that world's episode counter
    drop_cell: jax.Array  # int32, flat plan cell a rewarded brick landed on, -1 if none
    drop_height: jax.Array  # int16, the height that brick brought its cell to
    stride: jax.Array  # int8, the stride drawn (lets a relabelled episode be replayed)


@struct.dataclass
class FinalGrids:
    """Per world, the final plan-area grids of its last `M` episodes (a ring indexed by episode
    counter modulo M); `episode` says which episode a slot holds (-1: none yet)."""

    grids: jax.Array  # int16 (B, M, *plan_shape)
    episode: jax.Array  # int32 (B, M)


@struct.dataclass
class HindsightWorlds(Worlds):
    final_grids: FinalGrids


def plan_area(config: EnvConfig, grid: jax.Array) -> jax.Array:
    """The design-area part of a padded grid."""
    (pr, pc), (h, w) = config.pad, config.plan_shape
    return jax.lax.dynamic_slice(grid, (pr, pc), (h, w))


def drop_record(config: EnvConfig, grid_before: jax.Array, grid_after: jax.Array, terminated: jax.Array):
    """`(flat plan cell, height)` of the brick this step was rewarded for, cell -1 if none.

    Read from the grid change rather than re-deriving the action rule: a rewarded drop is one
    that changed a cell and did not end the episode (the ending drop scores 0, SPEC §5). In 2D a
    brick on a filled cell changes nothing and scores 0 against any binary design, as it would
    in the relabelled episode, so it needs no record either.
    """
    changed = (plan_area(config, grid_after) != plan_area(config, grid_before)).reshape(-1)
    cell = jnp.argmax(changed)
    height = plan_area(config, grid_after).reshape(-1)[cell]
    rewarded = changed.any() & ~terminated
    return jnp.where(rewarded, cell, -1).astype(jnp.int32), height.astype(jnp.int16)


def hindsight_rewards(config: EnvConfig, drop_cell: jax.Array, drop_height: jax.Array, design: jax.Array) -> jax.Array:
    """Rewards of recorded drops against another design (`design (..., *plan_shape)` with the
    leading shape of `drop_cell`), through the environment's one reward function."""
    flat = design.reshape(drop_cell.shape + (-1,)).astype(jnp.int32)
    wanted = jnp.take_along_axis(flat, jnp.maximum(drop_cell, 0)[..., None], axis=-1)[..., 0]
    reward = drop_reward(config, drop_height.astype(jnp.int32), wanted)
    return jnp.where(drop_cell >= 0, reward, 0.0).astype(jnp.float32)


class DRQNHER(DRQN):
    @functools.cached_property
    def ring_size(self) -> int:
        """Final grids kept per world: enough for every episode a buffer row can hold, sized by
        the episode's fewest steps without the stuck rule (an episode ended by it is rare, and a
        slot overwritten too early only drops that episode's relabelled copy)."""
        return self.per_world // episode_min_steps(self.env, self.env_params, stuck=False) + 2

    def _example_step(self) -> HindsightStep:
        base = super()._example_step()
        return HindsightStep(
            **{f.name: getattr(base, f.name) for f in dataclasses.fields(Step)},
            world=jnp.zeros((), jnp.int32),
            episode=jnp.zeros((), jnp.int32),
            drop_cell=jnp.zeros((), jnp.int32),
            drop_height=jnp.zeros((), jnp.int16),
            stride=jnp.zeros((), jnp.int8),
        )

    def memory_bytes(self) -> dict[str, int]:
        plan = math.prod(self.env.config.plan_shape)
        return {**super().memory_bytes(), "final_grids": self.config.num_envs * self.ring_size * (plan * 2 + 4)}

    def _initial_worlds(self, env_state, obs: jax.Array) -> HindsightWorlds:
        worlds = super()._initial_worlds(env_state, obs)
        n = self.config.num_envs
        final_grids = FinalGrids(
            grids=jnp.zeros((n, self.ring_size) + self.env.config.plan_shape, jnp.int16),
            episode=jnp.full((n, self.ring_size), -1, jnp.int32),
        )
        return HindsightWorlds(
            **{f.name: getattr(worlds, f.name) for f in dataclasses.fields(Worlds)}, final_grids=final_grids
        )

    def _world_step(self, worlds: HindsightWorlds, keys: jax.Array, action: jax.Array, env_params):
        """The environment's step, keeping the final grid of an ending episode, which the
        auto-reset would discard: its relabelled copy is scored against it."""
        env, n = self.env, self.config.num_envs
        obs, env_state, reward, terminated, truncated, info, stepped = jax.vmap(
            env.step_keeping_final_state, in_axes=(0, 0, 0, None)
        )(keys, worlds.env_state, action, env_params)
        done = terminated | truncated

        drop_cell, drop_height = jax.vmap(lambda b, a, t: drop_record(env.config, b, a, t))(
            worlds.env_state.grid, stepped.grid, terminated
        )
        step = HindsightStep(
            obs=worlds.obs.astype(jnp.int16),
            reset=worlds.reset,
            action=action.astype(jnp.int8),
            reward=reward,
            done=done,
            world=jnp.arange(n, dtype=jnp.int32),
            episode=worlds.episode,
            drop_cell=drop_cell,
            drop_height=drop_height,
            stride=info["stride"].astype(jnp.int8),
        )
        ring, rows, slot = worlds.final_grids, jnp.arange(n), worlds.episode % self.ring_size
        final = jax.vmap(lambda g: plan_area(env.config, g))(stepped.grid).astype(jnp.int16)
        final_grids = FinalGrids(
            grids=ring.grids.at[rows, slot].set(jnp.where(done[:, None, None], final, ring.grids[rows, slot])),
            episode=ring.episode.at[rows, slot].set(jnp.where(done, worlds.episode, ring.episode[rows, slot])),
        )
        return env_state, obs, reward, done, info, step, worlds.replace(final_grids=final_grids)

    def sample(self, state: RunnerState, key: jax.Array):
        """The first `hindsight_fraction` of the S windows are read as the relabelled copy:
        rewards against the episode's final grid (and, on dynamic tasks, that grid as the observed
        design), their steps masked out where the episode has not ended yet."""
        batch, obs, rewards, _ = super().sample(state, key)
        ring = state.worlds.final_grids
        slot = batch.episode % self.ring_size
        grids = ring.grids[batch.world, slot]  # (L, S, *plan_shape)
        ended = ring.episode[batch.world, slot] == batch.episode
        relabelled = (jnp.arange(rewards.shape[1]) < round(self.config.hindsight_fraction * self.config.batch_size))[
            None, :
        ]
        use = relabelled & ended
        rewards = jnp.where(use, hindsight_rewards(self.env.config, batch.drop_cell, batch.drop_height, grids), rewards)
        mask = jnp.where(relabelled, ended, True).astype(rewards.dtype)
        design = self.env.observation_layout.design
        if design is not None:
            flat = jnp.where(use[..., None], grids.reshape(grids.shape[:2] + (-1,)), obs[..., design])
            obs = obs.at[..., design].set(flat)
        return batch, obs, rewards, mask
