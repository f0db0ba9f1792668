"""Designs (SPEC §7): the fixed ones from the reference data, and the on-device generators.

Fixed designs (static tasks and the ten test designs of each dynamic task) are read from
`data/designs.json`, which holds the cells exactly as the reference implementation rasterised
them. Training designs of dynamic tasks are sampled by pure JAX generators:

- 1D: a random sine curve;
- 2D/3D: a random triangle, filled (dense) or its 8-connected outline (sparse), redrawn until
  its cell count is in range (rejection sampling in a `lax.while_loop`).

Why a design *bank*: gymnax auto-resets by computing a reset state at every step for every env.
Rejection-sampling a triangle there would cost more than the step itself (a vmapped while-loop
runs until the unluckiest env of the batch has its triangle). So `make` draws a bank of designs
once, on device, with these same generators, and `reset` draws an index into it. The bank size
and seed are parameters (`design_bank_size`, `design_seed`); a new bank is a new key away.

A bank never holds one of its task's ten test designs: a draw that equals one is redrawn (from
keys folded out of the design's own key, so every other design of the bank stays as it was).
Without this the agent could train on the very designs it is scored on: the rounded sine curves
take few distinct values, and a large bank draws some test curves verbatim.
"""

from __future__ import annotations

import functools
import json
from importlib import resources

import jax
import jax.numpy as jnp
import numpy as np

from snac_jax.config import PLAN_SIZE_1D, PLAN_SIZE_2D

HEIGHT_3D = 6
NUM_TEST_DESIGNS = 10

# Cell-count rules of the dynamic triangles (SPEC §7): count must satisfy low < count < high.
TRIANGLE_COUNT_RANGE = {
    (2, "dense"): (50, None),
    (2, "sparse"): (20, None),
    (3, "dense"): (50, 110),
    (3, "sparse"): (20, 110),
}
SINE_AMPLITUDE_RANGE = (3.0, 12.0)
SINE_FREQUENCIES = (1, 2, 3)


@functools.cache
def reference_designs() -> dict[str, dict]:
    """Every fixed design of `designs.json`, keyed by its variant name (e.g. `2d-static-dense`)."""
    text = resources.files("snac_jax").joinpath("data/designs.json").read_text()
    return json.loads(text)


def fixed_design(variant: str) -> np.ndarray:
    """A fixed design as an int array of the plan shape ((1, 30) in 1D, (20, 20) otherwise)."""
    designs = reference_designs()
    if variant not in designs:
        raise ValueError(f"unknown design {variant!r}; known designs: {sorted(designs)}")
    design = np.asarray(designs[variant]["design"], dtype=np.int16)
    return design.reshape(1, -1) if design.ndim == 1 else design


def max_bricks_for(design_stack: np.ndarray, dim: int) -> np.ndarray:
    """The brick budget of SPEC §1 for each design of a (K, rows, cols) stack, int32 (K,):
    sum(D) in 1D/3D, max(#cells, 30) in 2D."""
    design_stack = np.asarray(design_stack)
    if dim == 2:
        return np.maximum(np.sum(design_stack > 0, axis=(-2, -1)), 30).astype(np.int32)
    return np.sum(design_stack, axis=(-2, -1)).astype(np.int32)


# --- generators ------------------------------------------------------------------------------


def sine_curve(amplitude, frequency, phase) -> jax.Array:
    """round(k1 * sin(2*pi/30 * (k2 * x + phi)) + 20) over x = 0..29, shape (1, 30), int16."""
    x = jnp.arange(PLAN_SIZE_1D)
    curve = amplitude * jnp.sin(2 * jnp.pi / PLAN_SIZE_1D * (frequency * x + phase)) + 20
    return jnp.round(curve).astype(jnp.int16)[None, :]


def sample_sine(key: jax.Array) -> jax.Array:
    """A 1D dynamic design: k1 ~ U(3, 12), k2 uniform in {1, 2, 3}, phi ~ U(-pi, pi)."""
    k_amp, k_freq, k_phase = jax.random.split(key, 3)
    amplitude = jax.random.uniform(k_amp, minval=SINE_AMPLITUDE_RANGE[0], maxval=SINE_AMPLITUDE_RANGE[1])
    frequency = jax.random.choice(k_freq, jnp.asarray(SINE_FREQUENCIES))
    phase = jax.random.uniform(k_phase, minval=-jnp.pi, maxval=jnp.pi)
    return sine_curve(amplitude, frequency, phase)


def rasterise_triangle(vertices: jax.Array, filled: bool) -> jax.Array:
    """Cells of a triangle on the 20x20 plan, as a bool (20, 20) array.

    `vertices` is int (3, 2) of (row, col). The outline is three 8-connected digital lines
    (DDA with rounding); the filled triangle adds every cell whose centre lies inside.
    """
    n = PLAN_SIZE_2D
    rows, cols = jnp.meshgrid(jnp.arange(n), jnp.arange(n), indexing="ij")
    cells = jnp.zeros((n, n), dtype=bool)
    t = jnp.arange(n)  # n samples cover the longest possible line (n - 1 steps)
    for i in range(3):
        start, end = vertices[i], vertices[(i + 1) % 3]
        length = jnp.max(jnp.abs(end - start))
        frac = jnp.minimum(t, length) / jnp.maximum(length, 1)
        points = jnp.round(start[None, :] + frac[:, None] * (end - start)[None, :]).astype(jnp.int32)
        on_line = (rows[None] == points[:, 0, None, None]) & (cols[None] == points[:, 1, None, None])
        cells = cells | jnp.any(on_line, axis=0)
    if filled:
        signs = []
        for i in range(3):
            (r0, c0), (r1, c1) = vertices[i], vertices[(i + 1) % 3]
            signs.append((r1 - r0) * (cols - c0) - (c1 - c0) * (rows - r0))
        signs = jnp.stack(signs)
        inside = jnp.all(signs >= 0, axis=0) | jnp.all(signs <= 0, axis=0)
        cells = cells | inside
    return cells


def sample_triangle(key: jax.Array, dim: int, density: str) -> jax.Array:
    """A 2D/3D dynamic design: a random triangle redrawn until its cell count is in range."""
    low, high = TRIANGLE_COUNT_RANGE[(dim, density)]
    filled = density == "dense"

    def draw(k):
        vertices = jax.random.randint(k, (3, 2), 0, PLAN_SIZE_2D)
        return rasterise_triangle(vertices, filled)

    def rejected(carry):
        _, cells = carry
        count = jnp.sum(cells)
        ok = count > low
        if high is not None:
            ok = ok & (count < high)
        return ~ok

    def redraw(carry):
        k, _ = carry
        k, sub = jax.random.split(k)
        return k, draw(sub)

    key, sub = jax.random.split(key)
    _, cells = jax.lax.while_loop(rejected, redraw, (key, draw(sub)))
    height = HEIGHT_3D if dim == 3 else 1
    return cells.astype(jnp.int16) * height


def sample_design(key: jax.Array, dim: int, density: str | None, excluded: jax.Array | None = None) -> jax.Array:
    """One training design of a dynamic task, of the plan shape, int16, never equal to any of
    `excluded` (E, *plan_shape): a draw that equals one is redrawn with `fold_in(key, attempt)`."""

    def draw(k):
        return sample_sine(k) if dim == 1 else sample_triangle(k, dim, density)

    first = draw(key)
    if excluded is None:
        return first
    excluded = jnp.asarray(excluded, jnp.int16)

    def is_excluded(carry):
        _, design = carry
        return jnp.any(jnp.all(design[None] == excluded, axis=(1, 2)))

    def redraw(carry):
        attempt, _ = carry
        return attempt + 1, draw(jax.random.fold_in(key, attempt + 1))

    _, design = jax.lax.while_loop(is_excluded, redraw, (jnp.int32(0), first))
    return design


def dynamic_design_name(dim: int, density: str | None) -> str:
    """The designs.json prefix of a dynamic task's test designs (`1d-dynamic`, `2d-dynamic-dense`, ...)."""
    return "1d-dynamic" if dim == 1 else f"{dim}d-dynamic-{density}"


def test_designs(dim: int, density: str | None) -> np.ndarray:
    """The ten test designs of the dynamic task of (dim, density), (10, *plan_shape) int16."""
    name = dynamic_design_name(dim, density)
    return np.stack([fixed_design(f"{name}-test{i}") for i in range(NUM_TEST_DESIGNS)])


test_designs.__test__ = False  # a library function, not a pytest test


@functools.lru_cache(maxsize=32)
def design_bank(dim: int, density: str | None, size: int, seed: int) -> np.ndarray:
    """`size` training designs drawn on device from the generator, none equal to a test design of
    the task, as a host int16 array."""
    keys = jax.random.split(jax.random.key(seed), size)
    excluded = jnp.asarray(test_designs(dim, density))
    bank = jax.jit(jax.vmap(lambda k: sample_design(k, dim, density, excluded)))(keys)
    return np.asarray(bank)
