"""Data parallelism for training: the parallel worlds (and everything with one entry per world)
are split over the env mesh of `snac_jax.devices`; parameters and optimiser state are replicated.

A runner state keeps its per-world arrays under a `worlds` field (see `agents.ppo.Worlds`), with
the seed axis first and the world axis second; the driver shards exactly that field and jit's
sharding propagation does the rest (the gradient mean over worlds becomes an all-reduce).
`jax.devices()` lists every device of every process, so the same code spans hosts once
`jax.distributed.initialize()` ran.
"""

from __future__ import annotations

from typing import Any

import jax
from jax.sharding import NamedSharding, PartitionSpec as P

from snac_jax.devices import ENV_AXIS, check_divisible, env_mesh

__all__ = ["check_divisible", "env_mesh", "state_shardings"]


def state_shardings(state: Any, mesh) -> Any:
    """Shardings for a seed-batched runner state: `worlds` leaves split on axis 1 (axis 0 is the
    seed), everything else replicated."""
    replicated = NamedSharding(mesh, P())
    split = NamedSharding(mesh, P(None, ENV_AXIS))
    shardings = jax.tree.map(lambda _: replicated, state)
    return shardings.replace(worlds=jax.tree.map(lambda _: split, state.worlds))
