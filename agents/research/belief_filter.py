"""The row and column histogram filter of `pqn-belief` (agents/research/pqn_belief.py), as pure functions each
checked by hand in tests/test_belief.py: the belief's moves, its correction by the window's
padding, the design it expects around the robot and how well it knew the true position.

Why a module of their own: they are the filter's arithmetic, free of the network that runs them
(`BeliefQNetwork.run_filter`), so each is tested on its own and on real episodes.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from snac_jax.config import MAX_STRIDE

UNLIKELY = 1e-6  # the filter's weight on a position the window's padding contradicts


def expected_design_window(
    p_row: jax.Array, p_col: jax.Array, design: jax.Array, window_shape: tuple[int, int], outside: float
) -> jax.Array:
    """The design the robot expects in its window, `(..., wr, wc)`, under independent beliefs
    `p_row (..., rows)` and `p_col (..., cols)` over the plan `design (..., rows, cols)`; window
    cells off the plan read `outside` (the window shows padding there).

    Window cell (i, j) of a robot at plan (r, c) is plan cell (r + i - hr, c + j - hc), hr and hc
    the window's half sizes, so with the design padded by them it is padded cell (r + i, c + j):
    the expectation is `sum_r,c p_row[r] p_col[c] padded[r + i, c + j]`, i.e. `A @ padded @ B^T`
    with row i of A the row belief shifted right by i (and B likewise).
    """
    wr, wc = window_shape
    pad = [(0, 0)] * (design.ndim - 2) + [(wr // 2, wr // 2), (wc // 2, wc // 2)]
    padded = jnp.pad(design, pad, constant_values=outside)

    def shifted(p: jax.Array, size: int) -> jax.Array:  # (..., size, n + size - 1)
        lead = [(0, 0)] * (p.ndim - 1)
        return jnp.stack([jnp.pad(p, lead + [(i, size - 1 - i)]) for i in range(size)], axis=-2)

    return jnp.einsum("...ir,...rc,...jc->...ij", shifted(p_row, wr), padded, shifted(p_col, wc))


def shift_matrices(n: int) -> np.ndarray:
    """`(2 * MAX_STRIDE + 1, n, n)`: matrix k moves a one-hot belief by `k - MAX_STRIDE` cells,
    stopping at the ends (the plan's clipping, SPEC §3)."""
    offsets = np.arange(-MAX_STRIDE, MAX_STRIDE + 1)
    to = np.clip(np.arange(n)[None, :] + offsets[:, None], 0, n - 1)  # (offsets, from)
    return (to[:, :, None] == np.arange(n)[None, None, :]).astype(np.float32)


def move_belief(belief: jax.Array, p_cells: jax.Array, sign: jax.Array) -> jax.Array:
    """The belief `(..., n)` after a move of `sign` (-1, 0 or +1) along its axis by m cells with
    probability `p_cells[..., m]`, m = 0..MAX_STRIDE; sign 0 leaves it as it is."""
    moved = jnp.einsum("...i,kij->...kj", belief, jnp.asarray(shift_matrices(belief.shape[-1])))
    index = (sign[..., None] * jnp.arange(MAX_STRIDE + 1) + MAX_STRIDE).astype(jnp.int32)  # (..., m)
    return jnp.einsum("...m,...mj->...j", p_cells, jnp.take_along_axis(moved, index[..., None], axis=-2))


def padding_agrees(padding: jax.Array, n: int) -> jax.Array:
    """`(..., n)`: for each position 0..n-1 along an axis, whether the window line across it,
    `padding (..., w)` (True where the window shows padding), has padding exactly where the
    window reaches off the plan from that position."""
    w = padding.shape[-1]
    seen = np.arange(n)[:, None] + np.arange(w)[None, :] - w // 2  # (n, w): the plan cell each window cell shows
    off = (seen < 0) | (seen >= n)
    return jnp.all(padding[..., None, :] == jnp.asarray(off), axis=-1)


def correct_belief(belief: jax.Array, agrees: jax.Array) -> jax.Array:
    """Bayes' rule with a near-certain likelihood, after a floor of `UNLIKELY` under every
    position: a belief that has gone wrong (a move misread) moves to the positions the padding
    allows instead of staying where it contradicts the window."""
    belief = (belief + UNLIKELY) * jnp.where(agrees, 1.0, UNLIKELY)
    return belief / belief.sum(axis=-1, keepdims=True)


def belief_cross_entropy(p_row: jax.Array, p_col: jax.Array, position: jax.Array) -> jax.Array:
    """Mean over steps of -log P(true row) P(true column) under the belief, `position (..., 2)`:
    how well the belief the Q head read knew where the robot was (a metric, in the position
    loss's units; ln rows + ln cols when it guesses)."""
    picked = jnp.take_along_axis(p_row, position[..., 0:1], -1) * jnp.take_along_axis(p_col, position[..., 1:2], -1)
    return -jnp.log(jnp.maximum(picked, 1e-12)).mean()


def start_belief(n: int) -> jax.Array:
    """An episode starts at the plan's corner, row 0 and column 0 (SPEC §2)."""
    return jax.nn.one_hot(0, n)


def filter_step(
    belief: tuple[jax.Array, jax.Array],
    reset: jax.Array,
    p_cells: jax.Array,
    sign: jax.Array,
    window_padding: jax.Array,
) -> tuple[jax.Array, jax.Array]:
    """One step of the row and column filters, `belief = (b_row (B, rows), b_col (B, cols))`: back
    to the start where `reset`, else moved by the last action (`sign (B, 2)`: its row and column
    direction, 0 for a drop or no action) by `p_cells (B, MAX_STRIDE + 1)` cells, then corrected
    by the window's padding (`window_padding (B, wr, wc)`) along its centre column (rows) and
    centre row (columns)."""
    b_row, b_col = belief
    wr, wc = window_padding.shape[-2:]
    b_row = jnp.where(reset[:, None], start_belief(b_row.shape[-1]), move_belief(b_row, p_cells, sign[:, 0]))
    b_col = jnp.where(reset[:, None], start_belief(b_col.shape[-1]), move_belief(b_col, p_cells, sign[:, 1]))
    b_row = correct_belief(b_row, padding_agrees(window_padding[:, :, wc // 2], b_row.shape[-1]))
    b_col = correct_belief(b_col, padding_agrees(window_padding[:, wr // 2, :], b_col.shape[-1]))
    return b_row, b_col
