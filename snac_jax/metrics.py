"""Intersection over union (SPEC §8), the benchmark's score."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from snac_jax.state import EnvState


def iou(state: EnvState) -> jax.Array:
    """IoU of a state's built grid against its design, float32; works on batched states.

    The environment keeps sum(min(G, D)) and sum(max(G, D)) up to date at every drop, so this is
    one division. `grid_iou` computes the same number from scratch.
    """
    return (state.overlap / jnp.maximum(state.union, 1)).astype(jnp.float32)


def grid_iou(grid, design, dim: int) -> float:
    """IoU of a design-area grid (no padding) against a design, computed from the cells.

    1D and 3D: sum(min(G, D)) / sum(max(G, D)); 2D: |G>0 and D>0| / |G>0 or D>0|.
    """
    grid, design = np.asarray(grid), np.asarray(design)
    if dim == 2:
        grid, design = grid > 0, design > 0
        return float(np.sum(grid & design) / np.sum(grid | design))
    return float(np.sum(np.minimum(grid, design)) / np.sum(np.maximum(grid, design)))
