"""State and parameters of a SNAC environment (`flax.struct` pytrees, gymnax-compatible)."""

from __future__ import annotations

import jax
from flax import struct


@struct.dataclass
class EnvState:
    """One world. Coordinates are plan coordinates (row, col); 1D uses row 0.

    `overlap` and `union` are the running sums of min(G, D) and max(G, D) over the design area
    (SPEC §8), updated at the one cell a drop changes, so the IoU costs nothing per step.
    """

    grid: jax.Array  # padded world (SPEC §2): -1 padding, brick counts (0/1 in 2D)
    position: jax.Array  # int32 (2,), plan coordinates
    design: jax.Array  # int16 plan-shaped design of this episode
    max_bricks: jax.Array  # int32, the brick budget of this design
    bricks_used: jax.Array  # int32, N_b
    time: jax.Array  # int32, N_s (gymnax's name: `is_truncated` reads it)
    overlap: jax.Array  # int32, sum of min(G, D)
    union: jax.Array  # int32, sum of max(G, D)
    landmarks: jax.Array | None = None  # bool padded mask, with the landmarks or landmark_action switch
    # SPEC §14, only with the landmark_action switch: placements left this episode.
    landmarks_left: jax.Array | None = None  # int32
    # SPEC §15, only with the design_change switch: the step whose end brings the next design.
    change_step: jax.Array | None = None  # int32
    next_design: jax.Array | None = None  # int16 plan-shaped, the design in force from change_step on
    next_max_bricks: jax.Array | None = None  # int32, the next design's own brick budget


@struct.dataclass
class EnvParams:
    """Values the step reads but that never change shapes: vmap or replace them freely.

    `designs` holds the designs a reset draws from: one for a static task or a pinned test
    design, a bank of sampled training designs for a dynamic task (see `snac_jax.designs`).
    """

    designs: jax.Array  # int16 (K, *plan_shape)
    design_max_bricks: jax.Array  # int32 (K,)
    design_volume: jax.Array  # int32 (K,), sum of each design: the union of an empty grid
    stride_probs: jax.Array  # float32 (3,), P(d = 1, 2, 3)
    max_steps_in_episode: int = struct.field(pytree_node=True, default=600)


@struct.dataclass
class PrivilegedState:
    """What `SNACEnv.privileged` reveals of one world for training (SPEC §12); never an
    observation: an evaluated policy sees only `step`'s observation."""

    position: jax.Array  # int32 (2,), the true plan position (row, col; row 0 in 1D)
    built: jax.Array  # the plan part of the grid: bricks on each plan cell (0/1 in 2D)
    design: jax.Array  # int16 plan-shaped design of the episode
    stuck: jax.Array  # bool, the robot cannot move (SPEC §4; always False without obstacles)
