"""`pqn-belief`'s filter with a map of the bricks it laid (`brick_map=True`), as pure functions each
checked by hand in tests/test_belief_map.py: the belief is joint over rows and columns, and the
window's bricks are evidence of where the robot stands (`MappingBeliefQNetwork` in agents/research/pqn_belief.py
runs it).

Why: the row and column filters of `agents.research.belief_filter` correct the belief only where the window
reaches off the plan. Away from the plan's edges every position agrees with the padding, so a
misread stride leaves the robot a cell or two sideways for the rest of the episode (what
pqn-belief's notes measure on 2d-dynamic-sparse). The bricks it laid are the rest of what the
window carries: the robot keeps a map of where they went, under its belief at each drop, and a
position whose map disagrees with the bricks the window shows becomes unlikely. This is the
handcrafted policy's SLAM (SPEC §11) done with distributions instead of a point estimate.

The map per plan cell is the mean and the variance of its brick count under the belief at each
drop: a drop lands on the believed target cell with probability `p`, adding a Bernoulli(p)
brick; on the 0/1 grid of 2D (SPEC §5, capped) the mean is the chance the cell holds a brick.
The window's count at a cell is scored against the map with a Gaussian of the map's variance
plus `WINDOW_NOISE`, so one brick out of place costs a bounded number of nats and a wrong map
bends the belief rather than breaking it. The evidence needs the joint belief: a brick pattern
tells the row and the column together, which independent row and column beliefs cannot hold.

Honest acting: the map is built from the robot's own actions and belief, and scored against its
own window; nothing reads the true position or the true grid.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from agents.research.belief_filter import UNLIKELY, move_belief, padding_agrees
from snac_jax.transition import PADDING  # a window cell off the plan (SPEC §2)

WINDOW_NOISE = 0.25  # the variance added to the map's: a brick the map does not expect costs 1 / (2 * 0.25) = 2 nats


def start_joint(rows: int, cols: int) -> jax.Array:
    """An episode starts at the plan's corner, row 0 and column 0 (SPEC §2)."""
    return jnp.zeros((rows, cols)).at[0, 0].set(1.0)


def move_joint(belief: jax.Array, p_cells: jax.Array, sign: jax.Array) -> jax.Array:
    """The joint belief `(B, rows, cols)` after a move of `sign (B, 2)` (row and column direction,
    one of them 0) by m cells with probability `p_cells[:, m]`: `move_belief` along each axis."""
    batch, rows, cols = belief.shape

    def along_last(b: jax.Array, s: jax.Array) -> jax.Array:  # b (B, k, n): move each of the k lines along n
        k = b.shape[1]
        p = jnp.broadcast_to(p_cells[:, None, :], (batch, k, p_cells.shape[-1]))
        return move_belief(b, p, jnp.broadcast_to(s[:, None], (batch, k)))

    belief = along_last(belief, sign[:, 1])  # columns
    return jnp.swapaxes(along_last(jnp.swapaxes(belief, 1, 2), sign[:, 0]), 1, 2)  # rows


def shifted(grid: jax.Array, d_row: int, d_col: int) -> jax.Array:
    """`grid (B, rows, cols)` moved by (d_row, d_col), zeros where nothing moved in: cell (r, c) of
    the result is cell (r - d_row, c - d_col) of `grid`, 0 off the plan."""
    _, rows, cols = grid.shape
    padded = jnp.pad(grid, ((0, 0), (1, 1), (1, 1)))
    return padded[:, 1 - d_row : 1 - d_row + rows, 1 - d_col : 1 - d_col + cols]


def drop_target(belief: jax.Array, last_action: jax.Array, drops: tuple) -> jax.Array:
    """`(B, rows, cols)`: where the last action's brick went, under the belief the robot held when
    it dropped; all zeros after a move (the probability mass of a target off the plan, where a drop
    does nothing, is dropped too). `last_action (B, A + 1)` one-hot with a last "none" entry,
    `drops` per action `(is_drop, d_row, d_col)` (SPEC §3)."""
    target = jnp.zeros_like(belief)
    for action, (is_drop, d_row, d_col) in enumerate(drops):
        if is_drop:
            target = target + last_action[:, action, None, None] * shifted(belief, d_row, d_col)
    return target


def add_drop(mean: jax.Array, var: jax.Array, target: jax.Array, capped: bool) -> tuple[jax.Array, jax.Array]:
    """The map after a brick that landed on each cell with probability `target`: a Bernoulli
    brick added to the count (mean + p, variance + p (1 - p)), right in expectation however the
    drops correlate. `capped` (the 0/1 grid of 2D): the mean is the chance of a brick, max(m, p),
    and its variance m (1 - m). Drops made under one belief land on one true cell, so their
    chances do not combine as independent ones (m + (1 - m) p would make every cell of a spread
    belief certain after a few drops on one spot); the larger of the two is the chance that holds
    whichever way they correlate."""
    if capped:
        mean = jnp.maximum(mean, target)
        return mean, mean * (1.0 - mean)
    return mean + target, var + target * (1.0 - target)


def map_last_drop(
    mean: jax.Array,
    var: jax.Array,
    belief: jax.Array,
    last_action: jax.Array,
    reset: jax.Array,
    drops: tuple,
    capped: bool,
) -> tuple[jax.Array, jax.Array]:
    """The map `(mean, var)`, each `(B, rows, cols)`, after the last action's brick went in under
    the joint `belief` the robot dropped it with (`drop_target`, `add_drop`); empty where `reset`
    (a new episode's map). The one map update of the mapping filter and of `todo_compass`'s map."""
    mean, var = add_drop(mean, var, drop_target(belief, last_action, drops), capped)
    empty = jnp.zeros_like(mean)
    return jnp.where(reset[:, None, None], empty, mean), jnp.where(reset[:, None, None], empty, var)


def correlate(image: jax.Array, kernel: jax.Array) -> jax.Array:
    """`out[b, r, c] = sum_ij kernel[b, i, j] image[b, r + i, c + j]` for `image (B, R + kh - 1,
    C + kw - 1)` and `kernel (B, kh, kw)`: the window laid over every position of the plan."""
    _, kh, kw = kernel.shape
    rows, cols = image.shape[1] - kh + 1, image.shape[2] - kw + 1
    return sum(kernel[:, i, j, None, None] * image[:, i : i + rows, j : j + cols] for i in range(kh) for j in range(kw))


def brick_log_likelihood(window: jax.Array, mean: jax.Array, var: jax.Array) -> jax.Array:
    """`(B, rows, cols)`: log-likelihood, up to a constant, of the window's counts `window (B, wr,
    wc)` (raw values: padding and landmarks, below 0, carry no count) at each position, under
    the map: `sum -(w - mean)^2 / (2 (var + WINDOW_NOISE))` over the window cells on the plan,
    expanded into three correlations of the window with the padded map."""
    wr, wc = window.shape[1:]
    pad = ((0, 0), (wr // 2, wr // 2), (wc // 2, wc // 2))
    inv = jnp.pad(1.0 / (2.0 * (var + WINDOW_NOISE)), pad)
    mean = jnp.pad(mean, pad)
    counted = (window >= 0).astype(window.dtype)
    w = window * counted
    return -(correlate(inv, w * w) - correlate(2.0 * mean * inv, w) + correlate(mean * mean * inv, counted))


def correct_joint(belief: jax.Array, padding: jax.Array, log_likelihood: jax.Array) -> jax.Array:
    """Bayes' rule on the joint belief: the padding's near-certain likelihood along the window's
    centre column (rows) and centre row (columns), as `agents.research.belief_filter.correct_belief`, times the
    bricks' likelihood, after a floor of `UNLIKELY` under every position."""
    _, rows, cols = belief.shape
    wr, wc = padding.shape[1:]
    agrees = (
        padding_agrees(padding[:, :, wc // 2], rows)[:, :, None]
        & padding_agrees(padding[:, wr // 2, :], cols)[:, None, :]
    )
    weight = jnp.exp(log_likelihood - log_likelihood.max(axis=(1, 2), keepdims=True))
    belief = (belief + UNLIKELY) * jnp.where(agrees, 1.0, UNLIKELY) * weight
    return belief / belief.sum(axis=(1, 2), keepdims=True)


def mapping_filter_step(
    state: tuple[jax.Array, jax.Array, jax.Array],
    reset: jax.Array,
    p_cells: jax.Array,
    sign: jax.Array,
    last_action: jax.Array,
    window: jax.Array,
    drops: tuple,
    capped: bool,
    evidence_weight: float = 1.0,
):
    """One step: `state = (belief, mean, var)`, each `(B, rows, cols)`. The last action's brick goes
    into the map under the belief it was dropped with; where `reset` everything starts over
    (the corner, an empty map); the belief moves by the last action; then it is corrected by the
    window (`window (B, wr, wc)`, raw values): its padding and its bricks against the map, the
    bricks' log-likelihood times `evidence_weight` (1: Bayes' rule as if each step's window were
    new evidence; below 1 tempers it, as the window shows the same bricks step after step, and a
    map error repeats with them; bench/filter_replay.py compares weights). `capped`: the map holds
    the chance that a cell has a brick (`add_drop`) and the window's counts are read as 0/1 too,
    so a stack's height never enters the evidence (2D's 0/1 grid; 3D with `brick_occupancy`)."""
    belief, mean, var = state
    _, rows, cols = belief.shape
    mean, var = map_last_drop(mean, var, belief, last_action, reset, drops, capped)
    belief = jnp.where(reset[:, None, None], start_joint(rows, cols), move_joint(belief, p_cells, sign))
    if capped:  # the window read as the map is kept: a cell holds a brick or not (2D's window already is)
        window = jnp.where(window > 0, jnp.ones_like(window), window)
    belief = correct_joint(belief, window == PADDING, evidence_weight * brick_log_likelihood(window, mean, var))
    return belief, mean, var


def remaining_compass(p_row: jax.Array, p_col: jax.Array, design: jax.Array, built: jax.Array) -> jax.Array:
    """`(..., 5)`: where the design's unbuilt cells lie under the map, as the Q head reads them
    (`todo_compass`): the expected share of the design still unbuilt in the rows above the
    believed row, the rows below it, the columns left and right of the believed column, and in
    all. `design` and `built` `(..., rows, cols)` in bricks (`built` the map's mean), `p_row
    (..., rows)`, `p_col (..., cols)` the belief's marginals.

    Why: the window shows what is missing within reach only, and the GRU's few units cannot hold
    which of a solid design's cells are done; on 2d-static-dense more than half of the episodes
    end at the step limit (beyond.md). The map knows where the robot believes it laid its bricks."""
    remaining = jnp.maximum(design - built, 0.0)
    total = jnp.maximum(design.sum(axis=(-2, -1)), 1.0)[..., None]

    def before_after(p: jax.Array, line: jax.Array) -> tuple[jax.Array, jax.Array]:  # line (..., n): per row or column
        before = jnp.cumsum(line, axis=-1) - line  # the remaining design strictly before each line
        after = line.sum(axis=-1, keepdims=True) - before - line
        return (p * before).sum(axis=-1), (p * after).sum(axis=-1)

    above, below = before_after(p_row, remaining.sum(axis=-1))
    left, right = before_after(p_col, remaining.sum(axis=-2))
    return jnp.stack([above, below, left, right, remaining.sum(axis=(-2, -1))], axis=-1) / total


def drop_table(env_config) -> tuple:
    """Per action `(is_drop, d_row, d_col)` (`EnvConfig.actions`, SPEC §3), the landmark placement
    (SPEC §14, the index after the table's) `(0, 0, 0)`: where each drop's brick lands."""
    table = [tuple(map(int, row)) for row in env_config.actions]
    return tuple(table + [(0, 0, 0)] * (env_config.num_actions - len(table)))
