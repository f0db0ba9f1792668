"""The drops that would wall the robot in, read from its window (`safe_drops`, an option of the
PQN learners).

Why: under the obstacle rule (SPEC §4) a robot whose four neighbours all hold bricks or padding
is stuck, and whatever it does next ends the episode with the design unfinished. A learner that
is unsure where it stands drops bricks around the cell it takes for a design cell and can close
the last way out itself. Only a drop can do that: a move leaves free the cell it came from (it
stood there, and a move stops before the first cell that is not free), and a drop on a cell that
holds bricks already, or toward the padding, frees nothing and blocks nothing new. So refusing a
drop on the last free neighbour keeps the robot from ever being stuck. The window shows the four
neighbours, so the refusal reads the observation alone: the acting policy stays honest.

The price: a drop that would have walled the robot in and still scored (it lands, SPEC §4) is
never taken, so an episode that would have ended stuck goes on instead, toward the step limit or
the brick budget.

A free neighbour is one a move may enter: 0 in the window, or a landmark (SPEC §9: the grid holds
0 there and the window shows `LANDMARK_VALUE`). A drop on a landmark spends the brick and changes
nothing, so it closes nothing and is never refused.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from snac_jax.config import MOVE_DIRECTIONS, EnvConfig
from snac_jax.observation import LANDMARK_VALUE


def neighbour_drop_targets(config: EnvConfig) -> np.ndarray:
    """`(num_actions,)` int: for each neighbour drop of the action table, the index in the
    row-major window of the cell it lands on; -1 for every other action (moves, a drop on the
    robot's own cell, the landmark placement)."""
    rows, cols = config.window_shape
    centre_row, centre_col = rows // 2, cols // 2
    targets = np.full(config.num_actions, -1, np.int32)
    for action, (is_drop, d_row, d_col) in enumerate(config.actions):
        if is_drop and (d_row, d_col) != (0, 0):
            targets[action] = (centre_row + d_row) * cols + centre_col + d_col
    return targets


def require_obstacles(config: EnvConfig, task: str) -> None:
    """`safe_drops` refuses a world without the obstacle rule, where no robot is ever stuck."""
    if not config.obstacles:
        raise ValueError(
            f"safe_drops needs the obstacle rule (3D, or 2D with obstacles=true); {task} has none, "
            "so its robot is never stuck"
        )


def allowed_actions(config: EnvConfig, window: jax.Array) -> jax.Array:
    """`(..., num_actions)` bool from the raw window cells `(..., window_size)` (the start of the
    observation, SPEC §6): every action but a drop on the robot's only free neighbour."""
    rows, cols = config.window_shape
    centre = (rows // 2) * cols + cols // 2
    neighbours = window[..., [centre + d_row * cols + d_col for d_row, d_col in MOVE_DIRECTIONS]]
    free = (neighbours == 0) | (neighbours == LANDMARK_VALUE)
    targets = neighbour_drop_targets(config)
    target_cells = window[..., np.maximum(targets, 0)]
    closes_last_way_out = (targets >= 0) & (target_cells == 0) & (free.sum(-1, keepdims=True) == 1)
    return ~closes_last_way_out


def masked_q(q: jax.Array, allowed: jax.Array | None) -> jax.Array:
    """Q-values with the refused actions at -inf (`allowed` None: all of them allowed), so that
    argmax and max over actions, acting and bootstrapping alike, never pick one."""
    return q if allowed is None else jnp.where(allowed, q, -jnp.inf)


def random_allowed(key: jax.Array, allowed: jax.Array | None, shape: tuple[int, ...], num_actions: int) -> jax.Array:
    """A uniformly random allowed action per world (`allowed` None: any action), for exploration."""
    if allowed is None:
        return jax.random.randint(key, shape, 0, num_actions)
    return jax.random.categorical(key, jnp.where(allowed, 0.0, -jnp.inf), axis=-1, shape=shape)
