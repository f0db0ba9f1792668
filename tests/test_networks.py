"""Shared network pieces: the design encoder's strided convolution against `flax.linen.Conv`, and
its parameters, which checkpoints written before it must still fit."""

from __future__ import annotations

import flax.linen as nn
import jax
import numpy as np
import pytest

from agents.common.networks import DesignEncoder, StridedConv


@pytest.mark.slow
@pytest.mark.parametrize("shape", [(5, 20, 20, 1), (3, 10, 10, 16), (2, 7, 9, 2), (2, 1, 6, 1), (1, 2, 2, 3)])
def test_strided_conv_equals_flax_conv_with_the_same_parameters(shape):
    x = jax.random.normal(jax.random.key(1), shape)
    mine = StridedConv(16)
    params = mine.init(jax.random.key(0), x)
    params = jax.tree.map(lambda p: p + 0.1, params)  # a non-zero bias too
    reference = nn.Conv(16, (3, 3), strides=(2, 2), padding="SAME").apply(params, x)
    np.testing.assert_allclose(mine.apply(params, x), reference, atol=1e-5)


@pytest.mark.slow
def test_design_encoder_keeps_the_parameter_tree_of_flax_convs():
    """The same names and shapes as when the encoder used `nn.Conv`: older checkpoints load."""
    params = DesignEncoder(64).init(jax.random.key(0), np.zeros((2, 20, 20), np.float32))["params"]
    shapes = jax.tree.map(lambda p: p.shape, params)
    assert shapes == {
        "Conv_0": {"kernel": (3, 3, 1, 16), "bias": (16,)},
        "Conv_1": {"kernel": (3, 3, 16, 16), "bias": (16,)},
        "Dense_0": {"kernel": (400, 64), "bias": (64,)},
    }


@pytest.mark.slow
def test_strided_conv_inside_a_scan_matches_outside():
    """The reason for the class: it runs inside the learners' `lax.scan` loops; same numbers there."""
    x = jax.random.normal(jax.random.key(2), (4, 12, 12, 1))
    conv = StridedConv(8)
    params = conv.init(jax.random.key(0), x)
    grad = jax.grad(lambda p: (conv.apply(p, x) ** 2).sum())
    scanned = jax.lax.scan(lambda c, _: (c, grad(params)), 0, None, length=2)[1]
    # float32 sums of ~150 terms of order 1, which XLA may associate differently in and out of the
    # loop (a run measured 2.4e-5); a wrong convolution would be off by order 1.
    for inside, outside in zip(jax.tree.leaves(scanned), jax.tree.leaves(grad(params))):
        np.testing.assert_allclose(inside[1], outside, rtol=1e-4, atol=1e-4)
