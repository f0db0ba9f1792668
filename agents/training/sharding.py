"""Data parallelism for training: the parallel worlds (and everything with one entry per world)
are split over the env mesh of `snac_jax.devices`; parameters and optimiser state are replicated.

A runner state keeps its per-world arrays under a `worlds` field (see `agents.learners.ppo.Worlds`), with
the seed axis first and the world axis second; the driver shards exactly that field and jit's
sharding propagation does the rest (the gradient mean over worlds becomes an all-reduce).
The training mesh is built from `jax.devices()`, which lists every device of every process, so
the same code spans hosts once `jax.distributed.initialize()` ran: each process then holds its
share of the worlds, and host-side reads go through `host_value` (this process's copy of a
replicated value).
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from snac_jax.devices import ENV_AXIS, check_divisible, env_mesh

__all__ = ["check_divisible", "host_value", "replicate", "state_shardings", "training_mesh"]


def training_mesh(num_devices: int | None = None, num_envs: int | None = None):
    """The env mesh over the devices of every process (see `snac_jax.devices.env_mesh`)."""
    return env_mesh(num_devices, num_envs, global_devices=True)


def replicate(tree: Any, mesh) -> Any:
    """Every array of `tree` (the same values in every process) as a global array replicated
    over `mesh`, so that a jit over a mesh spanning processes can take it as an argument."""
    sharding = NamedSharding(mesh, P())

    def place(x):
        value = np.asarray(x)
        return jax.make_array_from_callback(value.shape, sharding, lambda index: value[index])

    return jax.tree.map(place, tree)


def host_value(tree: Any) -> Any:
    """This process's copy of every replicated array of `tree`, as NumPy."""
    return jax.tree.map(lambda x: np.asarray(x.addressable_data(0)) if isinstance(x, jax.Array) else x, tree)


def state_shardings(state: Any, mesh) -> Any:
    """Shardings for a seed-batched runner state: `worlds` leaves split on axis 1 (axis 0 is the
    seed), everything else replicated."""
    replicated = NamedSharding(mesh, P())
    split = NamedSharding(mesh, P(None, ENV_AXIS))
    shardings = jax.tree.map(lambda _: replicated, state)
    return shardings.replace(worlds=jax.tree.map(lambda _: split, state.worlds))
