"""The rules of several robots in one world (SPEC §13), as pure functions of one world.

Each robot's turn is the single-robot transition (`snac_jax.transition.transition`) applied to the
shared world with that robot's position; the only additions are the ones §13 states: a move
stops before a cell another robot stands on, a drop onto another robot does nothing, and the
robots after the one that ended the episode do not act. Both additions are expressed through
the transition's own arguments (a shorter stride, a move of stride 0), so the single-robot rules
are not copied here and one robot is the single-robot step exactly.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from snac_jax import observation
from snac_jax.config import MAX_STRIDE, EnvConfig
from snac_jax.env import draw_stride, random_words
from snac_jax.state import EnvState
from snac_jax.threefry import bits
from snac_jax.transition import transition

ROBOT_VALUE = -3.0
"""What a robot's window shows where another robot stands: below −1 (padding) and −2 (a
landmark), so it is told apart from every cell value (brick counts are >= 0)."""

STRIDE_STREAM = 2
"""`fold_in(step key, STRIDE_STREAM)` draws the strides of robots 1..N-1. Robot 0 draws its
stride from the step key's first word, as the single-robot env does; the reset reads the second
word and a landmark placement `fold_in(key, 1)`, so this stream is independent of all three."""


def max_robots(dim: int) -> int:
    """The most robots a plan holds: one per corner (2D/3D), one per end of the row (1D)."""
    return 2 if dim == 1 else 4


def start_positions(config: EnvConfig, num_robots: int) -> np.ndarray:
    """int32 (num_robots, 2): robot 0 at plan (0, 0) as the single robot; then the opposite
    corner, then (0, last column), then (last row, 0). In 1D the two ends of the row."""
    rows, cols = config.plan_shape
    corners = [(0, 0), (rows - 1, cols - 1), (0, cols - 1), (rows - 1, 0)]
    return np.asarray(corners[:num_robots], dtype=np.int32)


def draw_strides(key: jax.Array, stride_probs: jax.Array, num_robots: int) -> jax.Array:
    """int32 (num_robots,): each robot's stride for this step, drawn independently."""
    first = draw_stride(random_words(key)[0], stride_probs)[None]
    if num_robots == 1:
        return first
    others = draw_stride(bits(jax.random.fold_in(key, STRIDE_STREAM), num_robots - 1), stride_probs)
    return jnp.concatenate([first, others])


def _occupied(cells: jax.Array, others: jax.Array) -> jax.Array:
    """bool (len(cells),): does another robot stand on each of `cells` (plan coordinates)?"""
    return jnp.any(jnp.all(cells[:, None, :] == others[None, :, :], axis=-1), axis=-1)


def robot_turns(
    config: EnvConfig, world: EnvState, actions: jax.Array, strides: jax.Array
) -> tuple[EnvState, jax.Array, jax.Array]:
    """One step of every robot, in robot order (SPEC §13). `world.position` is (N, 2).

    Returns the world after the step, each robot's reward (N,) float32 and whether the episode
    terminated. N_s grows by one per step, not per robot.
    """
    num_robots = world.position.shape[0]
    table = jnp.asarray(np.asarray(config.actions, dtype=np.int32))
    distances = jnp.arange(1, MAX_STRIDE + 1)
    positions, time = world.position, world.time
    rewards, ended = [], jnp.asarray(False)
    for i in range(num_robots):
        own = positions[i]
        others = jnp.concatenate([positions[:i], positions[i + 1 :]])
        is_drop = table[actions[i], 0] == 1
        direction = table[actions[i], 1:]
        # Cells 1..MAX_STRIDE along the action's direction: free up to the first robot on them.
        # A drop's target is the first of them (its own cell for an own-cell drop, never taken).
        blocked = _occupied(own + distances[:, None] * direction, others)
        free = jnp.sum(jnp.cumprod(~blocked)).astype(jnp.int32)
        void = ended | (is_drop & blocked[0])
        action = jnp.where(void, 0, actions[i])  # a move of stride 0 stays; the stuck rule still holds
        stride = jnp.where(void, 0, jnp.minimum(strides[i], free))
        world, reward, terminated = transition(config, world.replace(position=own), action, stride)
        positions = positions.at[i].set(world.position)
        rewards.append(reward)  # 0 for a robot that did not act: it dropped nothing
        ended = ended | terminated
    world = world.replace(position=positions, time=time + 1)
    return world, jnp.stack(rewards), ended


def robots_in_windows(config: EnvConfig, positions: jax.Array) -> jax.Array:
    """bool (N, rows, cols): where each robot's window shows another robot."""
    num_robots = positions.shape[0]
    rows, cols = config.window_shape
    # A window's top-left cell is its robot's plan position in padded coordinates (SPEC §2).
    offsets = positions[None, :, :] + jnp.asarray(config.pad) - positions[:, None, :]  # (i, j, 2)
    seen = (jnp.arange(rows)[:, None] == offsets[..., 0, None, None]) & (
        jnp.arange(cols)[None, :] == offsets[..., 1, None, None]
    )
    others = ~np.eye(num_robots, dtype=bool)
    return jnp.any(seen & others[:, :, None, None], axis=1)


def observe_all(config: EnvConfig, world: EnvState) -> jax.Array:
    """float32 (N, obs_size): each robot's observation, laid out as `observation.layout(config)`,
    its window showing the other robots as `ROBOT_VALUE`."""
    per_robot = jax.vmap(lambda p: observation.observe(config, world.replace(position=p)))(world.position)
    if world.position.shape[0] == 1:
        return per_robot
    window = observation.layout(config).window
    marks = robots_in_windows(config, world.position).reshape(per_robot.shape[0], -1)
    return per_robot.at[:, window].set(jnp.where(marks, ROBOT_VALUE, per_robot[:, window]))
