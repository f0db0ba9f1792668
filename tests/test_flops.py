"""`bench/flops.py`: the matrix FLOPs of a traced function, by hand."""

import jax
import jax.numpy as jnp
import numpy as np

from bench.flops import count


def test_a_matrix_product_costs_two_flops_per_multiply_add():
    w, x = jnp.ones((8, 16)), jnp.ones((4, 8))
    assert count(lambda x: x @ w, x).total == 2 * 4 * 8 * 16


def test_a_scan_multiplies_its_body_by_its_length_and_vmap_by_its_batch():
    w, x = jnp.ones((8, 16)), jnp.ones((4, 8))
    scanned = count(lambda x: jax.lax.scan(lambda c, _: (c, c @ w), x, None, length=5)[1], x)
    assert scanned.total == 5 * 1024 and scanned.exact
    assert count(jax.vmap(lambda x: x @ w), jnp.ones((3, 4, 8))).total == 3 * 1024


def test_a_gradient_counts_the_backward_products():
    w, x = jnp.ones((8, 16)), jnp.ones((4, 8))
    # d/dx of sum(x @ w): the forward product and ones(4, 16) @ w.T.
    assert count(jax.grad(lambda x: (x @ w).sum()), x).total == 2 * 1024


def test_a_convolution_counts_each_output_times_its_kernel_and_a_while_loop_is_marked_inexact():
    x, k = jnp.ones((2, 10, 10, 3)), jnp.ones((3, 3, 3, 4))
    conv = lambda x: jax.lax.conv_general_dilated(x, k, (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC"))
    assert count(conv, x).total == 2 * (2 * 10 * 10 * 4) * (3 * 3 * 3)
    looped = count(
        lambda x: jax.lax.while_loop(lambda c: c[0] < 3, lambda c: (c[0] + 1, c[1] @ np.eye(8)), (0, x))[1],
        jnp.ones((4, 8)),
    )
    assert looped.total == 2 * 4 * 8 * 8 and not looped.exact


def test_a_cond_counts_its_costliest_branch_and_says_it_is_an_upper_bound():
    w, x = jnp.ones((8, 8)), jnp.ones((4, 8))
    flops = count(lambda x: jax.lax.cond(x[0, 0] > 0, lambda y: y @ w @ w, lambda y: y, x), x)
    assert flops.total == 2 * (2 * 4 * 8 * 8) and not flops.exact
    same = count(lambda x: jax.lax.cond(x[0, 0] > 0, lambda y: y @ w, lambda y: -y @ w, x), x)
    assert same.total == 2 * 4 * 8 * 8 and same.exact
