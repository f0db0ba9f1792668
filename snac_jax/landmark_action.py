"""The landmark placement action (SPEC §14): the robot marks its own cell with a landmark.

Only imported into the step when `EnvConfig.landmark_action` is on: without the switch the
state carries no `landmarks_left` and the step is the one of SPEC §5.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from snac_jax.config import PLAN_SIZE_2D, EnvConfig
from snac_jax.state import EnvState

MAX_LANDMARK_ACTION = PLAN_SIZE_2D * PLAN_SIZE_2D
"""More placements than plan cells could never all land."""


def check(dim: int, value: Any) -> int:
    """The `landmark_action` override as an int K, or a one-line `ValueError` naming what is allowed."""
    ok = isinstance(value, (int, np.integer)) and not isinstance(value, bool) and 0 <= value <= MAX_LANDMARK_ACTION
    if not ok:
        raise ValueError(
            f"landmark_action must be an int in 0..{MAX_LANDMARK_ACTION} (landmarks an episode may "
            f"place; 0 = off), got {value!r}"
        )
    if value and dim == 1:
        raise ValueError("landmark_action needs a 2D or 3D task; every 1D column belongs to the design")
    return int(value)


def reset_fields(config: EnvConfig, landmarks: jax.Array | None) -> dict[str, jax.Array]:
    """The state fields a fresh episode starts with: an (empty unless `landmarks=K`) mask and K
    placements left."""
    if landmarks is None:
        landmarks = jnp.zeros(config.grid_shape, dtype=bool)
    return {"landmarks": landmarks, "landmarks_left": jnp.asarray(config.landmark_action, jnp.int32)}


def place(config: EnvConfig, state: EnvState, action: jax.Array) -> EnvState:
    """Apply a placement to `state` (already stepped: the robot has not moved, the placement is
    a no-op row of the action table). It lands on the robot's cell when placements are left and
    the cell holds neither a brick nor a landmark; otherwise nothing changes (SPEC §14)."""
    row, col = state.position[0] + config.pad[0], state.position[1] + config.pad[1]
    placed = (
        (action == config.place_landmark_action)
        & (state.landmarks_left > 0)
        & (state.grid[row, col] == 0)
        & ~state.landmarks[row, col]
    )
    return state.replace(
        landmarks=state.landmarks.at[row, col].set(state.landmarks[row, col] | placed),
        landmarks_left=state.landmarks_left - placed.astype(jnp.int32),
    )
