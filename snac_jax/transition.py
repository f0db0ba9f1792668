"""The deterministic part of one step (SPEC §3-5), shared by 1D, 2D and 3D.

The stride is an argument: `SNACEnv.step_env` draws it, and replaying a recorded episode passes
the recorded one. Nothing here branches in Python on traced values; the configuration (static)
selects the action table, the obstacle rule, the binary clip and the reward scheme.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from snac_jax import design_change, landmark_action
from snac_jax.config import MAX_STRIDE, MOVE_DIRECTIONS, EnvConfig
from snac_jax.state import EnvState

PADDING = -1


def drop_reward(config: EnvConfig, height: jax.Array, design_height: jax.Array) -> jax.Array:
    """Reward for a brick that lands and brings its cell to `height` where the design wants
    `design_height` (SPEC §5). The one definition of the reward: hindsight relabelling reuses it."""
    if config.reward_scheme == "height":
        return jnp.where(height > design_height, -1.0, jnp.where(height == design_height, 10.0, 1.0))
    return jnp.where(height <= design_height, 5.0, 0.0)


# `MOVE_DIRECTIONS` as an array: the four directions of moves (actions 0..3) and of neighbour
# drops, in that order.
DIRECTIONS = np.asarray(MOVE_DIRECTIONS)


def rays(grid: jax.Array, padded_position: jax.Array) -> jax.Array:
    """(4, MAX_STRIDE): the cells 1..MAX_STRIDE away from the robot in each of `DIRECTIONS`,
    nearest first; everything the obstacle rule reads, in one gather. The padding is
    >= MAX_STRIDE wide, so every index stays inside the grid."""
    distances = np.arange(1, MAX_STRIDE + 1)
    offsets = DIRECTIONS[:, None, :] * distances[None, :, None]
    return grid[padded_position[0] + offsets[..., 0], padded_position[1] + offsets[..., 1]]


def _surrounded(around: jax.Array) -> jax.Array:
    """SPEC §4, the stuck rule: no neighbour is free (0) to move to. `around` is `rays(...)`."""
    return jnp.all(around[:, 0] != 0)


def is_stuck(config: EnvConfig, state: EnvState) -> jax.Array:
    """Whether the robot of `state` is stuck (never without the obstacle rule).

    `transition` applies the same rule to the state before the action and ends the episode on
    it; this asks it of any state (`SNACEnv.is_terminated`).
    """
    if not config.obstacles:
        return jnp.asarray(False)
    padded = state.position + jnp.asarray(config.pad)
    return _surrounded(rays(state.grid, padded))


def _advance(along: jax.Array, stride: jax.Array) -> jax.Array:
    """Obstacle rule: how many cells a move advances, cell by cell while the next cell is empty
    (0), up to `stride`. `along` holds the cells in the move's direction, nearest first."""
    advanced = jnp.zeros((), jnp.int32)
    clear = jnp.asarray(True)
    for distance in range(MAX_STRIDE):
        clear = clear & (along[distance] == 0)
        advanced = advanced + (clear & (stride > distance)).astype(jnp.int32)
    return advanced


def transition(
    config: EnvConfig, state: EnvState, action: jax.Array, stride: jax.Array
) -> tuple[EnvState, jax.Array, jax.Array]:
    """Apply `action` with stride `stride` (1..3). Returns (state, reward, terminated).

    Truncation by the step limit is not decided here: `state.time` counts the steps and the
    gymnax `step` compares it with `params.max_steps_in_episode`.
    """
    rows = config.actions + (((0, 0, 0),) if config.landmark_action else ())  # placement: a no-op move here
    table = jnp.asarray(np.asarray(rows, dtype=np.int32))
    is_drop = table[action, 0] == 1
    direction = table[action, 1:]
    offset = jnp.asarray(config.pad)
    padded = state.position + offset
    target = padded + direction

    if config.obstacles:
        # One gather of the four rays around the robot serves the stuck test (the nearest cell
        # of each ray), the move (the ray in the action's direction) and a neighbour drop
        # (that ray's nearest cell: the obstacle rule comes with the neighbour-drop actions).
        around = rays(state.grid, padded)
        stuck = _surrounded(around)  # judged before the action
        heading = jnp.all(direction[None, :] == jnp.asarray(DIRECTIONS), axis=1)
        along = jnp.sum(jnp.where(heading[:, None], around, 0), axis=0, dtype=around.dtype)
        moved = state.position + _advance(along, stride) * direction
        target_value = along[0]
    else:
        stuck = jnp.asarray(False)
        upper = jnp.asarray(config.plan_shape) - 1
        moved = jnp.clip(state.position + stride * direction, 0, upper)
        target_value = state.grid[target[0], target[1]]
    position = jnp.where(is_drop, state.position, moved)

    # Drops: onto the own cell, or onto a neighbour with the neighbour-drop action table.
    counted = is_drop & (target_value != PADDING)  # a drop toward padding spends nothing
    on_landmark = state.landmarks[target[0], target[1]] if state.landmarks is not None else jnp.asarray(False)
    placed = counted & ~on_landmark
    height = target_value.astype(jnp.int32) + 1
    new_value = jnp.minimum(height, 1) if config.binary_grid else height
    plan_target = jnp.clip(target - offset, 0, jnp.asarray(config.plan_shape) - 1)
    design_height = state.design[plan_target[0], plan_target[1]].astype(jnp.int32)
    old_value = jnp.maximum(target_value.astype(jnp.int32), 0)
    grid = state.grid.at[target[0], target[1]].set(jnp.where(placed, new_value, target_value).astype(state.grid.dtype))
    overlap = state.overlap + jnp.where(
        placed, jnp.minimum(new_value, design_height) - jnp.minimum(old_value, design_height), 0
    )
    union = state.union + jnp.where(
        placed, jnp.maximum(new_value, design_height) - jnp.maximum(old_value, design_height), 0
    )
    bricks_used = state.bricks_used + counted.astype(jnp.int32)

    out_of_bricks = counted & (bricks_used >= state.max_bricks)
    terminated = out_of_bricks | stuck
    reward = jnp.where(placed & ~terminated, drop_reward(config, height, design_height), 0.0)

    new_state = state.replace(
        grid=grid,
        position=position,
        bricks_used=bricks_used,
        time=state.time + 1,
        overlap=overlap,
        union=union,
    )
    if config.landmark_action:
        new_state = landmark_action.place(config, new_state, action)
    if config.design_change is not None:
        new_state = design_change.apply(config, new_state)
    return new_state, reward.astype(jnp.float32), terminated
