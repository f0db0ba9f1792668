"""The observation vector (SPEC §6): window, N_b, N_s, [design], [true position]."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from snac_jax.config import EnvConfig
from snac_jax.state import EnvState

LANDMARK_VALUE = -2.0


def window(config: EnvConfig, state: EnvState) -> jax.Array:
    """The window of the padded grid centred on the robot, float32 of `config.window_shape`.

    In padded coordinates the window's top-left corner is the robot's plan position, so the
    slice start is the position itself.
    """
    view = jax.lax.dynamic_slice(state.grid, (state.position[0], state.position[1]), config.window_shape)
    view = view.astype(jnp.float32)
    if state.landmarks is not None:
        marks = jax.lax.dynamic_slice(state.landmarks, (state.position[0], state.position[1]), config.window_shape)
        view = jnp.where(marks, LANDMARK_VALUE, view)
    return view


def observe(config: EnvConfig, state: EnvState) -> jax.Array:
    """Flat float32 observation of length `config.obs_size`."""
    parts = [
        window(config, state).reshape(-1),
        jnp.stack([state.bricks_used, state.time]).astype(jnp.float32),
    ]
    if config.dynamic:
        parts.append(state.design.reshape(-1).astype(jnp.float32))
    if config.gps:
        position = state.position[1:] if config.dim == 1 else state.position
        parts.append(position.astype(jnp.float32))
    return jnp.concatenate(parts)
