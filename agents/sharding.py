"""Data parallelism for training: the parallel worlds (and everything with one entry per world)
are split over a one-axis mesh of all devices; parameters and optimiser state are replicated.

A runner state keeps its per-world arrays under a `worlds` field (see `agents.ppo.Worlds`), with
the seed axis first and the world axis second; the driver shards exactly that field, and jit's
sharding propagation does the rest (gradients become all-reduces). `jax.devices()` lists every
device of every process, so the same code spans hosts once `jax.distributed.initialize()` ran.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

WORLD_AXIS = "worlds"


def world_mesh(devices=None) -> Mesh:
    """A one-axis mesh named `worlds` over `devices` (default: all devices)."""
    devices = jax.devices() if devices is None else devices
    return Mesh(np.asarray(devices), (WORLD_AXIS,))


def check_divisible(num_envs: int, mesh: Mesh) -> None:
    size = mesh.shape[WORLD_AXIS]
    if num_envs % size:
        raise ValueError(f"num_envs ({num_envs}) must be a multiple of the number of devices ({size})")


def state_shardings(state: Any, mesh: Mesh) -> Any:
    """Shardings for a seed-batched runner state: `worlds` leaves split on axis 1, all else replicated."""
    replicated = NamedSharding(mesh, P())
    split = NamedSharding(mesh, P(None, WORLD_AXIS))
    shardings = jax.tree.map(lambda _: replicated, state)
    return shardings.replace(worlds=jax.tree.map(lambda _: split, state.worlds))
