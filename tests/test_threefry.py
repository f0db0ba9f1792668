"""`snac_jax.threefry` returns exactly what `jax.random` returns, so using it changes no stream."""

import jax
import numpy as np
import pytest

from snac_jax import threefry


def test_fold_in_words_equal_jax_fold_in_under_jit_and_vmap():
    keys = jax.random.split(jax.random.key(123), 257)
    expected = jax.vmap(lambda k: jax.random.key_data(jax.random.fold_in(k, 0)))(keys)
    first, second = jax.jit(jax.vmap(threefry.fold_in_words))(keys)
    np.testing.assert_array_equal(np.stack([first, second], -1), expected)


@pytest.mark.parametrize("num", [1, 2, 7, 4096])
def test_split_and_bits_equal_jax_random(num):
    key = jax.random.key(num)
    np.testing.assert_array_equal(
        jax.random.key_data(threefry.split(key, num)), jax.random.key_data(jax.random.split(key, num))
    )
    np.testing.assert_array_equal(jax.jit(threefry.bits, static_argnums=1)(key, num), jax.random.bits(key, (num,)))


def test_other_key_implementations_fall_back_to_jax_random():
    key = jax.random.key(0, impl="rbg")
    np.testing.assert_array_equal(
        jax.random.key_data(threefry.split(key, 3)), jax.random.key_data(jax.random.split(key, 3))
    )
    words = threefry.fold_in_words(key)
    np.testing.assert_array_equal(np.stack(words), jax.random.key_data(jax.random.fold_in(key, 0))[:2])
