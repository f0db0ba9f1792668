"""Designs that change within an episode (SPEC §15): the draw at reset, the switch in the step,
and the evaluation protocol's fixed schedule.

Only imported into the step when `EnvConfig.design_change` is on: without the switch the state
carries no change fields and the step is the one of SPEC §5.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from snac_jax.config import EnvConfig
from snac_jax.state import EnvParams, EnvState


def check(dynamic: bool, value: Any, max_steps: int, pinned: bool, bank_size: int) -> tuple[int, int] | None:
    """The `design_change` override as `(a, b)` (or None), or a one-line `ValueError` naming what
    is allowed: two ints with 1 <= a <= b < max_steps, on a dynamic task with at least two designs."""
    if value is None:
        return None
    allowed = f"design_change must be two ints (a, b) with 1 <= a <= b < max_steps={max_steps}"
    pair = tuple(value) if isinstance(value, (tuple, list)) else ()
    ints = len(pair) == 2 and all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in pair)
    if not ints or not 1 <= pair[0] <= pair[1] < max_steps:
        raise ValueError(f"{allowed}, got {value!r}")
    if not dynamic:
        raise ValueError("design_change applies to dynamic tasks only (a static task has one design)")
    if pinned:
        raise ValueError(
            "design_change cannot be combined with test_design: a pinned design has no other to change "
            "to (the evaluation protocol pairs the test designs itself, SPEC §15)"
        )
    if bank_size < 2:
        raise ValueError(f"design_change needs a design bank of at least 2 designs, got design_bank_size={bank_size}")
    return (int(pair[0]), int(pair[1]))


def _fields(params: EnvParams, change_step: jax.Array, next_index: jax.Array) -> dict[str, jax.Array]:
    return {
        "change_step": jnp.asarray(change_step, jnp.int32),
        "next_design": params.designs[next_index],
        "next_max_bricks": params.design_max_bricks[next_index],
    }


def reset_fields(config: EnvConfig, key: jax.Array, params: EnvParams, design_index: jax.Array) -> dict[str, jax.Array]:
    """Training: the change step uniform in a..b and the next design uniform among the bank's
    other designs, both from the reset key, so an episode's change is fixed at its start."""
    a, b = config.design_change
    key_step, key_next = jax.random.split(jax.random.fold_in(key, 3))
    change_step = jax.random.randint(key_step, (), a, b + 1, dtype=jnp.int32)
    k = params.designs.shape[0]
    if k == 1:
        next_index = jnp.zeros((), jnp.int32)
    else:
        shift = 1 + jax.random.randint(key_next, (), 0, k - 1, dtype=jnp.int32)
        next_index = (jnp.asarray(design_index, jnp.int32) + shift) % k
    return _fields(params, change_step, next_index)


def scheduled_step(config: EnvConfig, design_index: Any, num_designs: int) -> Any:
    """The evaluation protocol's change step for design i of K: a + floor(i (b - a) / (K - 1)),
    the K steps spread evenly over a..b (SPEC §15)."""
    a, b = config.design_change
    return a + (design_index * (b - a)) // max(num_designs - 1, 1)


def schedule(config: EnvConfig, params: EnvParams, state: EnvState, design_index: jax.Array) -> EnvState:
    """The evaluation protocol's fixed change for an episode on `params.designs[i]` (the ten test
    designs): design (i + 1) mod K at `scheduled_step`, the same for every policy, so results compare."""
    k = params.designs.shape[0]
    index = jnp.asarray(design_index, jnp.int32)
    return state.replace(**_fields(params, scheduled_step(config, index, k), (index + 1) % k))


def apply(config: EnvConfig, state: EnvState) -> EnvState:
    """After the step that brings `time` to `change_step`: the next design is in force. The IoU
    sums are recomputed over the plan against it, and the budget becomes the bricks spent plus
    the new design's own budget (SPEC §15)."""
    (pr, pc), (h, w) = config.pad, config.plan_shape
    built = jnp.maximum(state.grid[pr : pr + h, pc : pc + w].astype(jnp.int32), 0)
    design = state.next_design.astype(jnp.int32)
    switch = state.time == state.change_step
    return state.replace(
        design=jnp.where(switch, state.next_design, state.design),
        max_bricks=jnp.where(switch, state.bricks_used + state.next_max_bricks, state.max_bricks),
        overlap=jnp.where(switch, jnp.sum(jnp.minimum(built, design)), state.overlap),
        union=jnp.where(switch, jnp.sum(jnp.maximum(built, design)), state.union),
    )
