"""The observation vector (SPEC §6): window, N_b, N_s, [design], [true position].

`ObservationLayout` is the one definition of where each part sits in the flat vector; `observe`
builds the vector in that order, and everything that reads an observation back (the networks,
the renderer, the handcrafted policy, hindsight relabelling) slices it through the layout.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

from snac_jax.config import EnvConfig
from snac_jax.state import EnvState

LANDMARK_VALUE = -2.0


@dataclasses.dataclass(frozen=True)
class ObservationLayout:
    """Offsets of the parts of the flat observation of one environment configuration.

    The observation stays a flat float32 vector (gymnax wrappers and the golden traces rely on
    it); this says how to read it. Slicing helpers work on NumPy and JAX arrays with any leading
    batch axes.
    """

    window_shape: tuple[int, int]
    plan_shape: tuple[int, int]
    window: slice  # the window's cells, row-major
    bricks_used: int  # index of N_b, the bricks dropped so far
    time: int  # index of N_s, the steps taken so far
    design: slice | None  # the design's plan cells, row-major (dynamic tasks)
    position: slice | None  # the true plan position: (col,) in 1D, (row, col) in 2D/3D (gps)
    size: int

    @property
    def window_size(self) -> int:
        return self.window.stop - self.window.start

    @property
    def design_size(self) -> int:
        return self.plan_shape[0] * self.plan_shape[1]

    @property
    def counters(self) -> slice:
        """N_b and N_s, side by side."""
        return slice(self.bricks_used, self.time + 1)

    def window_cells(self, obs):
        """The window of `obs (..., size)` as `(..., rows, cols)`."""
        return obs[..., self.window].reshape(obs.shape[:-1] + self.window_shape)

    def design_cells(self, obs):
        """The design of `obs (..., size)` as `(..., *plan_shape)`; dynamic tasks only."""
        if self.design is None:
            raise ValueError("this task's observation holds no design (static task)")
        return obs[..., self.design].reshape(obs.shape[:-1] + self.plan_shape)


@functools.cache
def layout(config: EnvConfig) -> ObservationLayout:
    """The layout of `observe(config, ·)` (cached: an `EnvConfig` is hashable)."""
    window_size = config.window_shape[0] * config.window_shape[1]
    offset = window_size + 2
    design = position = None
    if config.dynamic:
        design = slice(offset, offset + config.design_size)
        offset = design.stop
    if config.gps:
        position = slice(offset, offset + (1 if config.dim == 1 else 2))
        offset = position.stop
    return ObservationLayout(
        window_shape=config.window_shape,
        plan_shape=config.plan_shape,
        window=slice(0, window_size),
        bricks_used=window_size,
        time=window_size + 1,
        design=design,
        position=position,
        size=offset,
    )


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
    """Flat float32 observation, laid out as `layout(config)` says."""
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
